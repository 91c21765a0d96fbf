"""The studies' one job runner: run the main recipe's config in-process from Hydra overrides.

A study (``recipes/paper_tables.py``, ``ablations.py``, ``weighting_study.py``, ``convergence_study.py``,
``q_accuracy_study.py``, ``benchmark_tables.py``) is a list of *cells*, each a dict of labels and ``"overrides"``;
:func:`run_cells` runs every (cell, seed) with a budget (the overrides that come first; :func:`study_budget` reads
the studies' budgets from ``configs/study_budgets.yaml``), locally or through a Hydra launcher (Slurm, Ray), and
skips the runs whose ``results.json`` exists, so a study resumes where it stopped.

Locally, a cell's seeds train together in one process (:func:`run_cell_seeds`: one
:func:`~torchrl_wbrm.training.seeds.run_seeds` job, the seeds one after another), and
``jobs`` processes run the cells in parallel. Each seed's run directory (:func:`cell_dir`) holds what a separate run
writes there, so whatever reads a study's output finds the same files.
"""
from __future__ import annotations

import copy
import functools
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from torchrl_wbrm.configs import CONFIG_DIR

__all__ = [
    "LABELS",
    "SEEDS_RECORD",
    "cell_dir",
    "compose_recipe_config",
    "finished_results",
    "run_cell",
    "run_cell_seeds",
    "run_cells",
    "run_overrides",
    "study_budget",
]

#: The labels of a cell that name its run directory (:func:`cell_dir`) and go into its results under ``"study"``.
LABELS = ("block", "env", "setting", "method")

#: The file, in a cell's seed-parent directory, that records the cell's last multi-seed job (:func:`run_cell_seeds`).
SEEDS_RECORD = "seeds.json"

ROOT = Path(__file__).resolve().parents[2]


def study_budget(name: str) -> list[str]:
    """The overrides of the study budget ``name`` in ``configs/study_budgets.yaml`` (``quiet``, ``quick``, ``table``,
    ``table_quick``, ``q_accuracy``, ``weighting``, ``convergence``, ``convergence_quick``), another budget's spliced in
    where the file names it by alias::

        >>> study_budget("weighting")[-3:] == study_budget("quiet")
        True
    """
    from omegaconf import OmegaConf

    budgets = OmegaConf.to_container(OmegaConf.load(CONFIG_DIR / "study_budgets.yaml"))
    if name not in budgets:
        raise ValueError(f"no study budget {name!r} in {CONFIG_DIR / 'study_budgets.yaml'}; "
                         f"the budgets are: {', '.join(budgets)}")
    flat = []
    for entry in budgets[name]:
        flat.extend(entry if isinstance(entry, list) else [entry])
    return flat


def compose_recipe_config(overrides: list[str], config_name: str = "wbrm_offline"):
    """``configs/<config_name>.yaml`` composed with ``overrides`` (and ``threads=1``), as a Hydra ``DictConfig``: a
    copy of the process's one composition of those overrides (a study asks for each cell's config more than once:
    whether its seeds are finished, then to run them)."""
    return copy.deepcopy(_composed(tuple(overrides), config_name))


@functools.lru_cache(maxsize=256)
def _composed(overrides: tuple[str, ...], config_name: str):
    from hydra import compose, initialize_config_dir

    from torchrl_wbrm.training.config import register_configs

    register_configs()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose(config_name, overrides=[*overrides, "threads=1"])


def finished_results(run_dir: str | os.PathLike, cfg) -> dict | None:
    """The results of the finished run in ``run_dir`` (``results.json``, a diverged run's too), or ``None`` if there
    is none; refused (:func:`~torchrl_wbrm.training.resume.check_finished_config`) if it ran with other settings than
    ``cfg``, so that a study never reports a run of another config as this one's."""
    from torchrl_wbrm.training.config import config_as_dict
    from torchrl_wbrm.training.resume import check_finished_config

    done = Path(run_dir) / "results.json"
    if not done.is_file():
        return None
    results = json.loads(done.read_text())
    if not isinstance(results.get("config"), dict):
        raise ValueError(f"{done} holds results without the config they ran with (key 'config'), so they cannot be "
                         f"told to be this config's; delete that run to redo it.")
    check_finished_config(done, results["config"], config_as_dict(cfg))
    return results


def run_overrides(
    overrides: list[str], run_dir: str | os.PathLike, *, extra_results: dict | None = None, config_name: str = "wbrm_offline"
) -> dict:
    """Compose ``configs/<config_name>.yaml`` with ``overrides``, train with one torch thread and return the results
    (with the run's ``wall_seconds``).

    A finished run (:func:`finished_results`: its ``results.json`` exists, and it ran with this config) is not run
    again, and one with only a checkpoint resumes from it, so an interrupted study resumes where it stopped.
    ``extra_results`` are merged into the saved results (e.g. the study cell's labels).
    """
    import torch

    from torchrl_wbrm.training.results import write_json
    from torchrl_wbrm.training.trainer import WBRMTrainer

    run_dir = Path(run_dir)
    cfg = compose_recipe_config(overrides, config_name)
    results = finished_results(run_dir, cfg)
    if results is not None:
        return results
    start = time.perf_counter()
    torch.set_num_threads(1)
    # an interrupted cell (a checkpoint, no results) continues; its config must match the checkpoint's
    resume = (run_dir / "checkpoint.pt").is_file()
    results = WBRMTrainer(cfg, run_dir, progress=False, resume=resume).run()
    results.update(extra_results or {})
    results["wall_seconds"] = time.perf_counter() - start
    write_json(run_dir / "results.json", results)
    return results


def cell_dir(out: str | os.PathLike, cell: dict, seed: int, *, labels=LABELS) -> Path:
    """``out/<block>/<env>/<setting>/<method>/seed<seed>`` (one path part per label): where one study cell's run for
    one seed lives."""
    name = "/".join(str(cell[k]) for k in labels).replace(" ", "_")
    return Path(out) / name / f"seed{seed}"


def _overrides(cell: dict, seed: int | None, budget: list[str]) -> list[str]:
    """A cell's overrides after the budget (the cell wins), then its seed."""
    return [*budget, *cell["overrides"], *([f"seed={seed}"] if seed is not None else [])]


def run_cell(cell: dict, seed: int, budget: list[str], out: str, labels=LABELS) -> str:
    """Run one study cell (``cell["overrides"]`` after ``budget``) for one seed; its labels go into the results
    under ``"study"``. Skipped if its results exist."""
    run_dir = cell_dir(out, cell, seed, labels=labels)
    run_overrides(_overrides(cell, seed, budget), run_dir, extra_results={"study": {k: cell[k] for k in labels}})
    return str(run_dir)


def run_cell_seeds(cell: dict, seeds, budget: list[str], out: str, labels=LABELS) -> list[str]:
    """Run one study cell (``cell["overrides"]`` after ``budget``) for its unfinished ``seeds`` in this process, each
    into its :func:`cell_dir`, with the cell's labels in its results under ``"study"``; returns the seeds' run
    directories.

    A finished seed (:func:`finished_results`, which refuses a ``results.json`` of another config) is skipped; one
    that a job stopped before the job's end left without its labels gets them, so the reports count it. A seed
    whose directory holds a checkpoint (an interrupted single run) resumes from it on its own, as :func:`run_cell`
    does, and so does a cell with one unfinished seed (a single run, which checkpoints). The other seeds train as one
    job: the cell's config with ``seeds=[...]``, by :func:`~torchrl_wbrm.training.seeds.run_seeds` into the seeds'
    parent directory, so each seed's directory holds what its separate run writes there (its checkpoint included: an
    interrupted seed resumes on its own). Each seed's ``wall_seconds`` is its share of the job's wall time (the
    job's divided by its number of seeds), and ``"job"`` records the job's seeds and wall time. The job's combined results (``"kind": "seeds"``) go to :data:`SEEDS_RECORD` in the parent
    directory, not to a ``results.json`` there: each seed's run is read once, from its own directory.
    """
    from torchrl_wbrm.keys import CHECKPOINT
    from torchrl_wbrm.training.results import write_json

    study = {k: cell[k] for k in labels}
    dirs = {int(s): cell_dir(out, cell, int(s), labels=labels) for s in seeds}
    alone, together = [], []
    for seed, run_dir in dirs.items():
        results = finished_results(run_dir, compose_recipe_config(_overrides(cell, seed, budget)))
        if results is None:
            (alone if (run_dir / CHECKPOINT).is_file() else together).append(seed)
        elif results.get("study") != study:  # finished by a job stopped before it labelled its seeds
            write_json(run_dir / "results.json", {**results, "study": study})
    if len(together) == 1:
        alone, together = sorted(alone + together), []
    for seed in alone:
        run_cell(cell, seed, budget, out, labels)
    if together:
        _run_seeds_job(cell, together, budget, dirs, study)
    return [str(d) for d in dirs.values()]


def _run_seeds_job(cell: dict, seeds: list[int], budget: list[str], dirs: dict[int, Path], study: dict) -> None:
    """``seeds`` of ``cell`` as one :func:`~torchrl_wbrm.training.seeds.run_seeds` job (see :func:`run_cell_seeds`)."""
    import torch

    from torchrl_wbrm.training.results import write_json
    from torchrl_wbrm.training.seeds import run_seeds

    parent = dirs[seeds[0]].parent
    cfg = compose_recipe_config([*_overrides(cell, None, budget), f"seeds=[{','.join(map(str, seeds))}]"])
    torch.set_num_threads(1)
    start = time.perf_counter()
    combined = run_seeds(cfg, parent, progress=False)
    wall = time.perf_counter() - start
    (parent / "results.json").unlink(missing_ok=True)  # the seeds' results are read from their own directories
    job = {"seeds": seeds, "wall_seconds": wall}
    runs = []
    for run in combined["runs"]:
        path = dirs[int(run["seed"])] / "results.json"
        results = json.loads(path.read_text()) if path.is_file() else dict(run)
        results.update(study=study, wall_seconds=wall / len(seeds), job=job)
        write_json(path, results)
        runs.append(results)
    write_json(parent / SEEDS_RECORD, {**combined, "runs": runs, "study": study, "wall_seconds": wall})


def run_cells(cells: list[dict], seeds, budget: list[str], out: str | os.PathLike, *, jobs: int = 2,
              labels=LABELS, launcher: str | None = None, launcher_args=()) -> None:
    """Every (cell, seed), each in its :func:`cell_dir`.

    By default each cell's seeds train together in one process (:func:`run_cell_seeds`: one multi-seed job, the
    finished seeds skipped), with ``jobs`` local processes over the cells (joblib; one torch thread each) and a
    tqdm bar. With ``launcher`` (a Hydra launcher: ``submitit_local``, ``submitit_slurm``, ``ray``;
    ``pip install -e '.[sweeps]'``) each cell is one Hydra multirun of ``recipes/wbrm_offline.py`` over the seeds,
    one job per seed, with ``launcher_args`` (e.g. ``hydra.launcher.partition=cpu``); the launcher returns when its
    jobs have finished, and the cell's labels are then written into each run's results under ``"study"``, as the
    local runs do.
    """
    seeds = list(seeds)
    print(f"{len(cells) * len(seeds)} runs ({len(cells)} cells x {len(seeds)} seeds) into {out}"
          + ("" if launcher else ", each cell's seeds in one process"), flush=True)
    if launcher:
        for cell in cells:
            _launch_cell(cell, seeds, budget, Path(out), labels, launcher, list(launcher_args))
        return
    from joblib import Parallel, delayed
    from tqdm.auto import tqdm

    runner = Parallel(n_jobs=jobs, return_as="generator_unordered")
    for _ in tqdm(runner(delayed(run_cell_seeds)(cell, seeds, budget, str(out), labels) for cell in cells),
                  total=len(cells), unit="cell"):
        pass


def _launch_cell(cell: dict, seeds: list[int], budget: list[str], out: Path, labels, launcher: str,
                 launcher_args: list[str]) -> None:
    from torchrl_wbrm.training.results import write_json

    todo = [s for s in seeds if finished_results(cell_dir(out, cell, s, labels=labels),
                                                 compose_recipe_config(_overrides(cell, s, budget))) is None]
    if not todo:
        return
    sweep = cell_dir(out, cell, 0, labels=labels).parent
    cmd = [sys.executable, str(ROOT / "recipes" / "wbrm_offline.py"), "-m", f"hydra/launcher={launcher}",
           *launcher_args, *_overrides(cell, None, budget), "threads=1", f"seed={','.join(map(str, todo))}",
           f"hydra.sweep.dir={sweep}", "hydra.sweep.subdir=seed${seed}"]
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, cwd=ROOT, env={**os.environ, "MPLBACKEND": "Agg"})
    for seed in todo:
        path = cell_dir(out, cell, seed, labels=labels) / "results.json"
        if path.is_file():
            results = json.loads(path.read_text())
            results["study"] = {k: cell[k] for k in labels}
            write_json(path, results)
