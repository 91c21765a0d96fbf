"""Several seeds of one configuration in one process: ``python recipes/wbrm_offline.py seeds=[0,1,2]``.

Each seed is a :class:`~torchrl_wbrm.training.trainer.WBRMTrainer` of its own (``<run dir>/seed<s>``, built with
``seed=s``), run by the trainer's own loop (:meth:`~torchrl_wbrm.training.trainer.WBRMTrainer.run`) one seed after
another: its data, its networks' initialisation, its batches, its evaluations, its checkpoints and its results are
those of a separate run with that seed, bit for bit. What the seeds share is the process: its start-up and imports
are paid once. The seeds are not stepped together (their updates under ``torch.vmap`` over stacked parameters):
measured, that saves too little of a run's wall time for a second way of stepping them (:doc:`/performance`).

A multi-seed run is resumed (``resume=<run dir>``, :func:`run_seeds`' ``resume``) seed by seed: finished seeds are
kept, a seed with a checkpoint continues from it, the others run anew. A seed that diverges is recorded as diverged
(its ``results.json`` says where) and the others go on.

The run directory's ``results.json`` holds every seed's results under ``"runs"`` and the aggregate over the seeds
(mean and 95% Student-t interval of each final figure, :func:`~torchrl_wbrm.evaluation.stats.mean_ci`) under
``"aggregate"``; :func:`~torchrl_wbrm.training.reporting.load_results` reads it as the seeds' runs.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

from omegaconf import OmegaConf

from torchrl_wbrm.keys import RESULTS
from torchrl_wbrm.evaluation.stats import mean_ci
from torchrl_wbrm.training.config import PreparedConfig, WBRMConfig, config_as_dict, prepare_config
from torchrl_wbrm.training.results import json_safe, write_json
from torchrl_wbrm.training.trainer import WBRMTrainer

__all__ = ["aggregate", "run_seeds", "seed_config", "summarise_seeds"]


def _logger_for(loggers: dict | None, seed: int):
    """Seed ``seed``'s logger: ``loggers[seed]`` (``None`` if absent), or without ``loggers`` the one its config
    names (the trainer's ``logger="config"``)."""
    return "config" if loggers is None else loggers.get(int(seed))


def seed_config(cfg: WBRMConfig, seed: int) -> WBRMConfig:
    """``cfg`` as the separate run with ``seed`` (``seeds`` unset): the config a seed's trainer runs and records."""
    node = OmegaConf.structured(cfg)
    node.seed, node.seeds = int(seed), None
    return OmegaConf.to_object(node)


# ---------------------------------------------------------------------- results
def aggregate(runs: list[dict]) -> dict:
    """The final figures over the finished seeds: ``{figure: {"mean", "low", "high", "half_width", "stderr",
    "n"}}`` (95% Student-t, :func:`~torchrl_wbrm.evaluation.stats.mean_ci`), for every number each seed's
    ``final`` holds."""
    finished = [r for r in runs if r.get("status", "finished") == "finished"]
    out = {}
    if not finished:
        return out
    keys = [k for k, v in finished[0].get("final", {}).items() if isinstance(v, (int, float)) and k != "step"]
    for key in keys:
        values = [r["final"].get(key) for r in finished]
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
            continue
        ci = mean_ci(values)
        out[key] = {"mean": ci.mean, "low": ci.low, "high": ci.high, "half_width": ci.half_width,
                    "stderr": ci.stderr, "n": ci.n}
    return json_safe(out)


def _combined(cfg: WBRMConfig, runs: list[dict], *, timing: dict, task=None) -> dict:
    statuses = [r.get("status", "finished") for r in runs]
    return json_safe({
        "status": "finished" if all(s == "finished" for s in statuses) else "diverged",
        "kind": "seeds",
        "env": cfg.env.name,
        "algo": cfg.algo,
        "seeds": [int(s) for s in cfg.seeds],
        "seeds_diverged": [int(r["seed"]) for r in runs if r.get("status", "finished") != "finished"],
        "aggregate": {"final": aggregate(runs), "level": 0.95},
        "runs": runs,
        "timing": timing,
        "config": config_as_dict(cfg, task),
    })


def _earlier_seeds(cfg: WBRMConfig, run_dir: Path) -> tuple[dict[int, dict], list[int]]:
    """A resumed multi-seed run's seeds: ``(finished, checkpointed)``, the finished seeds' results (their
    ``results.json``, reused only for this config: :func:`~torchrl_wbrm.training.resume.check_finished_config`) and
    the seeds whose folder holds a checkpoint (an interrupted seed of a run trained one seed at a time)."""
    import json

    from torchrl_wbrm.keys import CHECKPOINT
    from torchrl_wbrm.training.resume import check_finished_config

    finished, checkpointed = {}, []
    for seed in cfg.seeds:
        seed_dir = run_dir / f"seed{seed}"
        done = seed_dir / RESULTS
        if done.is_file():
            try:
                results = json.loads(done.read_text())
            except (json.JSONDecodeError, UnicodeDecodeError) as err:
                raise ValueError(f"Cannot resume: {done} is damaged ({err}); delete it to run seed {seed} "
                                 f"again.") from None
            if not (isinstance(results, dict) and isinstance(results.get("config"), dict)):
                raise ValueError(f"Cannot resume: {done} holds no config (key 'config'), so it cannot be told to be "
                                 f"this run's seed {seed}; delete it to run that seed again.")
            check_finished_config(done, results["config"], config_as_dict(seed_config(cfg, seed)))
            finished[int(seed)] = results
            continue
        if (seed_dir / CHECKPOINT).is_file():
            checkpointed.append(int(seed))
    return finished, checkpointed


def run_seeds(cfg, run_dir, *, progress: bool = True, loggers: dict | None = None, resume: bool = False) -> dict:
    """Train ``cfg.seeds`` in one process, one after another, into ``run_dir`` (``run_dir/seed<s>`` per seed) and
    write ``run_dir/results.json`` (every seed's results under ``"runs"``, the aggregate under ``"aggregate"``).

    ``cfg`` is prepared once (:func:`~torchrl_wbrm.training.config.prepare_config`; or given prepared, as the recipe
    does); each seed is a :class:`~torchrl_wbrm.training.trainer.WBRMTrainer` of its
    :meth:`~torchrl_wbrm.training.config.PreparedConfig.for_seed`, run by its own loop:
    what it writes in its folder is what a separate run with that seed writes. ``cfg.overwrite``: an earlier run in
    ``run_dir`` is replaced whole (its ``results.json`` and every ``seed<s>/`` folder's outputs, the seeds this run
    does not train included). ``resume``: continue an interrupted multi-seed run in ``run_dir``: its finished seeds
    are kept (their results reused, for this config only), a seed whose folder holds a checkpoint resumes from it,
    and the others run anew. Returns the combined results.
    """
    from torchrl_wbrm.training.rundir import clear_run_outputs, holds_run

    prepared = cfg if isinstance(cfg, PreparedConfig) else prepare_config(cfg)  # once, for every seed
    cfg = prepared.config
    if not cfg.seeds:
        raise ValueError("run_seeds needs cfg.seeds, a list of seeds.")
    run_dir = Path(run_dir)
    start = time.perf_counter()
    finished, checkpointed = _earlier_seeds(cfg, run_dir) if resume else ({}, [])
    if not resume and cfg.overwrite and holds_run(run_dir):
        clear_run_outputs(run_dir)  # the earlier multi-seed run goes whole: no stale seed<s>/ outlives it
    runs_by_seed: dict[int, dict] = dict(finished)
    timing = {"setup": 0.0, "training": 0.0}
    for seed in (int(s) for s in cfg.seeds):
        if seed in finished:
            continue
        if resume and seed not in checkpointed:  # an unfinished seed without a checkpoint runs anew
            clear_run_outputs(run_dir / f"seed{seed}")
        t0 = time.perf_counter()
        trainer = WBRMTrainer(prepared.for_seed(seed), run_dir / f"seed{seed}", progress=progress,
                              logger=_logger_for(loggers, seed), resume=seed in checkpointed)
        t1 = time.perf_counter()
        runs_by_seed[seed] = trainer.run()
        timing["setup"] += t1 - t0
        timing["training"] += time.perf_counter() - t1
    runs = [runs_by_seed[int(s)] for s in cfg.seeds]
    timing["total"] = time.perf_counter() - start + prepared.task.check_seconds  # the checks' data read too
    results = _combined(cfg, runs, timing=timing, task=prepared.task)
    results["wall_seconds"] = timing["total"]
    write_json(run_dir / RESULTS, results)
    return results


def summarise_seeds(results: dict) -> str:
    """A few lines: each seed's headline figure and status, and the mean ± 95% CI over the seeds."""
    figure = next((k for k in ("regret", "return") if k in results["aggregate"]["final"]), None)
    lines = [f"env {results['env']}  algo {results['algo']}  seeds {results['seeds']}"]
    for run in results["runs"]:
        value = (run.get("final") or {}).get(figure)
        status = run.get("status", "finished")
        shown = "n/a" if not isinstance(value, (int, float)) else f"{value:.4f}"
        lines.append(f"  seed {run['seed']}: {figure} {shown}" + ("" if status == "finished" else f"  ({status})"))
    if figure is not None:
        agg = results["aggregate"]["final"][figure]
        half = agg["half_width"]
        lines.append(f"{figure} over {agg['n']} seeds: {agg['mean']:.4f} ± "
                     f"{'n/a' if half is None else format(half, '.4f')} (95% CI)")
    return "\n".join(lines)
