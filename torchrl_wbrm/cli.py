"""The recipes' command-line entry points (Hydra apps), installed with the package.

    wbrm-offline [overrides]              # = python recipes/wbrm_offline.py [overrides] = python -m torchrl_wbrm
    wbrm-make-dataset [overrides]         # = python recipes/make_dataset.py [overrides]

Both compose their config from the YAML shipped in the package (:data:`torchrl_wbrm.configs.CONFIG_DIR`), so they
run from any directory after ``pip install``; the scripts under ``recipes/`` in a clone call these same functions.
Run directories and datasets are written relative to the directory the command is started in.
"""
from __future__ import annotations

import shlex
import sys
import time
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.utils import get_original_cwd
from omegaconf import DictConfig, OmegaConf

from torchrl_wbrm.keys import CHECKPOINT, METADATA, RESULTS
from torchrl_wbrm.configs import CONFIG_DIR
from torchrl_wbrm.tasks import get_task
from torchrl_wbrm.training import WBRMTrainer, register_configs
from torchrl_wbrm.training.results import write_json
from torchrl_wbrm.training.resume import read_run_record
from torchrl_wbrm.training import stops
from torchrl_wbrm.training.rundir import RunDirClaim
from torchrl_wbrm.training.stops import RunInterrupted
from torchrl_wbrm.training.config import PreparedConfig, prepare_config
from torchrl_wbrm.training.logging import finish_logger, make_logger
from torchrl_wbrm.training.reporting import summarise

__all__ = ["wbrm_offline", "make_dataset"]

register_configs()


#: settings of a run's own overrides that a resume does not repeat (``overwrite=true`` would clear the run)
NOT_RESUMED = ("resume", "overwrite")


def _override_key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")


def with_run_overrides(args: list[str]) -> list[str]:
    """The command-line overrides ``args`` of a resume (``resume=X``) with the run's own overrides first.

    A run started with overrides (``env=lqr_exp3 q.lr=0.003``) is resumed with the same config: they are read from
    the run's Hydra record (``X/.hydra/overrides.yaml``, which a resume rewrites with them, so a second resume finds
    them too) and put before ``args``, which win: a key given in ``args`` is not repeated. Without ``resume=`` or
    without a record, ``args`` are returned as they are.

        >>> with_run_overrides(["q.steps=10"])
        ['q.steps=10']
    """
    given = [a for a in args if _override_key(a) == "resume" and "=" in a]
    if not given:
        return list(args)
    record = Path(given[-1].split("=", 1)[1].strip("'\"")) / ".hydra" / "overrides.yaml"
    if not record.is_file():  # the guard says what is missing
        return list(args)
    keys = {_override_key(a) for a in args}
    saved = read_run_record(record)  # data: only the recipe's own settings and offered values, nothing to load or run
    return [*(o for o in saved if _override_key(o) not in keys and _override_key(o) not in NOT_RESUMED), *args]


def recipe_command() -> str:
    """How this recipe was started, for the resume command it prints: ``wbrm-offline``, ``python -m torchrl_wbrm``
    or ``python <script>``."""
    script = Path(sys.argv[0])
    if script.name == "__main__.py" and script.parent.name == "torchrl_wbrm":
        return "python -m torchrl_wbrm"
    if script.suffix != ".py":  # the installed console script
        return script.name
    return f"python {shlex.quote(sys.argv[0])}"


def wbrm_offline() -> None:
    """``wbrm-offline [overrides]`` (``python recipes/wbrm_offline.py``, ``python -m torchrl_wbrm``): the recipe,
    with a resume's run overrides restored (:func:`with_run_overrides`), so ``resume=X`` alone continues the run."""
    command = recipe_command()
    try:
        sys.argv[1:] = with_run_overrides(sys.argv[1:])
    except ValueError as err:  # a run record holding more than the recipe's settings: one line, nothing applied
        raise SystemExit(f"Refused (nothing was written): {err}") from None
    hydra.main(config_path=str(CONFIG_DIR), config_name="wbrm_offline", version_base="1.3")(RecipeRun(command))()


class RecipeRun:
    """One invocation of the recipe, Hydra's task function: the Hydra callback
    (:class:`~torchrl_wbrm.training.hydra_guard.RunDirGuard`) hands it the config it prepared and the run
    directory's claim (:meth:`take_prepared`, from its ``on_job_start``), and Hydra then calls it with the composed
    config.

    Args:
        command: how the recipe was started (:func:`recipe_command`), for the resume command it prints.
    """

    def __init__(self, command: str = stops.RECIPE_COMMAND) -> None:
        self.command = command
        self.prepared: PreparedConfig | None = None
        self.claim: RunDirClaim | None = None

    def take_prepared(self, prepared: PreparedConfig, claim: RunDirClaim | None = None) -> None:
        """Keep the config :class:`~torchrl_wbrm.training.hydra_guard.RunDirGuard` prepared for this run, and its
        claim on the run directory."""
        self.prepared, self.claim = prepared, claim

    def __call__(self, cfg: DictConfig) -> None:
        prepared, claim, self.prepared, self.claim = self.prepared, self.claim, None, None
        _wbrm_offline_app(cfg, prepared, claim, self.command)


def _wbrm_offline_app(cfg: DictConfig, prepared: PreparedConfig | None, claim: RunDirClaim | None,
                      command: str) -> None:
    """Deep Weighted Bellman Residual Minimization, offline: stage 1 fits the density ratio ŵ, stage 2 fits Q*.

    Writes results.json, history.json, training_curve.png, evaluation.png, logs/ and checkpoint.pt in the run
    directory.
    """
    start = time.perf_counter()
    run_dir = Path(cfg.resume) if cfg.resume else Path(HydraConfig.get().runtime.output_dir)
    # the config merged, resolved and validated once, with its env's task: by the Hydra callback (RunDirGuard), or
    # here, before any data are collected, when the app runs without it (a multirun's job)
    prepared = prepared or prepare_config(cfg)
    if cfg.seeds:
        return _run_seeds(prepared, cfg, run_dir, command, claim)
    try:
        trainer = _trainer(prepared, run_dir, cfg, claim)
        trainer.logger = make_logger(
            cfg.logger, run_dir, f"wbrm_{cfg.env.name}_seed{cfg.seed}", OmegaConf.to_container(cfg, resolve=True)
        )
        results = trainer.run()
    except KeyboardInterrupt:  # before training started (data collection), or a second Ctrl-C
        if (run_dir / CHECKPOINT).is_file():
            print(f"Interrupted; {run_dir / CHECKPOINT} holds the last checkpoint. Resume with: "
                  f"{stops.resume_command(run_dir, command)}", file=sys.stderr)
        else:
            print(f"Interrupted before the first checkpoint; no checkpoint was written to {run_dir}.", file=sys.stderr)
        sys.exit(130)
    except RunInterrupted as err:
        print(err.with_command(command), file=sys.stderr)
        sys.exit(err.exit_code)
    except OSError as err:  # a full or read-only disk, the run directory removed: one line, the file and the disk
        _stopped_on(err, cfg, run_dir, command)
    finish_logger(trainer.logger)  # the wandb run ends with the run (finished or diverged), not at the process's exit
    results["wall_seconds"] = time.perf_counter() - start + prepared.task.check_seconds  # the checks' data read
    try:
        write_json(run_dir / RESULTS, results)
    except OSError as err:
        _stopped_on(err, cfg, run_dir, command)
    if results.get("status") == "diverged":
        print(results["diverged"]["message"], file=sys.stderr)
        print(f"run directory: {run_dir} (results.json has status 'diverged'; checkpoint.pt is the last finite state)",
              file=sys.stderr)
        sys.exit(2)
    print(summarise(results))
    print(f"run directory: {run_dir}")


def _trainer(prepared, run_dir: Path, cfg, claim: RunDirClaim | None) -> WBRMTrainer:
    """The run's trainer, holding ``claim``; what it refuses once the data are built (a resume on data that differ
    from the checkpoint's, a setting the data cannot carry out) is one line, exit status 1, before any training."""
    try:
        return WBRMTrainer(prepared, run_dir, logger=None, resume=bool(cfg.resume), claim=claim)
    except ValueError as err:
        if cfg.verbose:
            import traceback

            traceback.print_exc()
        print(f"Refused: {' '.join(str(err).split())}", file=sys.stderr)
        sys.exit(1)


def _stopped_on(err: OSError, cfg, run_dir: Path, command: str) -> None:
    """A run stopped by the file system (a full or read-only disk, its directory removed): one line naming the file
    and why (the traceback only with ``verbose=true``), exit status 1."""
    if cfg.verbose:
        import traceback

        traceback.print_exc()
    where = f" ({err.filename})" if getattr(err, "filename", None) and str(err.filename) not in str(err) else ""
    checkpoint = run_dir / CHECKPOINT
    kept = (f" {checkpoint} holds the last checkpoint; resume with: {stops.resume_command(run_dir, command)}"
            if checkpoint.is_file() else "")
    print(f"Stopped: {' '.join(str(err).split())}{where}.{kept}", file=sys.stderr)
    sys.exit(1)


def _run_seeds(prepared, cfg: DictConfig, run_dir: Path, command: str, claim: RunDirClaim | None) -> None:
    """``seeds=[...]``: the seeds trained in one process (:func:`torchrl_wbrm.training.seeds.run_seeds`), each in
    ``run_dir/seed<s>``; ``run_dir/results.json`` holds them all and the aggregate. ``claim`` (``run_dir``'s) is held
    until they end."""
    from torchrl_wbrm.training.seeds import run_seeds, summarise_seeds

    resume = (f"Resume with: {stops.resume_command(run_dir, command)} (the finished seeds are kept; a seed with a "
              f"checkpoint continues from it, the others run again)")
    try:
        # each seed's trainer makes its logger in its folder (cfg.logger), after its own checks
        results = run_seeds(prepared, run_dir, resume=bool(cfg.resume))
    except RunInterrupted as err:  # a seed trained one at a time stopped at a step, after a checkpoint
        print(f"{err.signal_name} received: seed {err.run_dir.name.removeprefix('seed')} stopped in stage "
              f"{err.stage!r} at step {err.step}, checkpoint written to {err.run_dir / CHECKPOINT}. {resume}",
              file=sys.stderr)
        sys.exit(err.exit_code)
    except KeyboardInterrupt:
        print(f"Interrupted. {resume}", file=sys.stderr)
        sys.exit(130)
    except OSError as err:
        _stopped_on(err, cfg, run_dir, command)
    except ValueError as err:  # a seed's folder refused (its checkpoint, its config): one line
        if cfg.verbose:
            import traceback

            traceback.print_exc()
        print(f"Refused: {' '.join(str(err).split())}", file=sys.stderr)
        sys.exit(1)
    finally:
        if claim is not None:
            claim.release()
    print(summarise_seeds(results))
    print(f"run directory: {run_dir}")
    if results["seeds_diverged"]:
        for run in results["runs"]:
            if run.get("status") == "diverged":
                print(f"seed {run['seed']}: {run['diverged']['message']}", file=sys.stderr)
        sys.exit(2)


def refuse(err: Exception, command: str) -> None:
    """A refused setting or output: one line on stderr (no traceback), exit status 2."""
    print(f"{command}: refused: {err}", file=sys.stderr)
    sys.exit(2)


def minari_ids(cfg) -> list[str]:
    """``format=minari``'s two ids: ``<minari_namespace>/expert-v0`` and ``<minari_namespace>/behaviour-v0``, the
    namespace ``make_dataset/<env.name>_seed<seed>`` by default (apart from the examples' ``examples/<env>``)."""
    namespace = cfg.minari_namespace or f"make_dataset/{cfg.env.name}_seed{cfg.seed}"
    return [f"{namespace}/expert-v0", f"{namespace}/behaviour-v0"]


def check_minari_out(cfg, out: Path) -> None:
    """Before any collecting: the two ids are valid and new under ``out`` (unless ``overwrite=true``)."""
    from torchrl_wbrm.data.minari_data import check_new_minari_ids

    ids = minari_ids(cfg)
    setting = f"minari_namespace=<name> (now {ids[0].rsplit('/', 1)[0]!r}) or overwrite=true (replaces them)"
    check_new_minari_ids(ids, out, setting=setting, overwrite=cfg.overwrite)


def check_torchrl_out(out: Path, overwrite: bool) -> None:
    """Before any collecting: ``out`` is new or empty, or (``overwrite=true``) holds only a dataset saved by
    :meth:`~torchrl_wbrm.data.OfflineDatasets.save`; other files are never written beside nor removed."""
    from torchrl_wbrm.data.datasets import PARTS

    if out.exists() and not out.is_dir():
        raise FileExistsError(f"out={out} is a file; make_dataset writes a dataset directory: choose another out=.")
    entries = sorted(p.name for p in out.iterdir()) if out.is_dir() else []
    if not entries:
        return
    ours = {METADATA, *PARTS}
    if not (out / METADATA).is_file():
        raise FileExistsError(f"out={out} is a non-empty directory that holds no dataset ({', '.join(entries[:5])}"
                              f"{', ...' if len(entries) > 5 else ''}); nothing was collected. make_dataset writes "
                              f"into a new or empty directory: choose another out=.")
    if not overwrite:
        raise FileExistsError(f"out={out} already holds a dataset; nothing was collected. Set overwrite=true to "
                              f"replace it, or choose another out=.")
    others = [name for name in entries if name not in ours]
    if others:
        raise FileExistsError(f"out={out} holds a dataset and other files ({', '.join(others[:5])}); overwrite=true "
                              f"replaces only a directory that holds a dataset alone: move them, or choose another "
                              f"out=.")


def _remove_dataset(out: Path) -> None:
    """Remove a saved dataset (``metadata.json`` first, so a half-removed one is never read as whole)."""
    import shutil

    from torchrl_wbrm.data.datasets import PARTS

    (out / METADATA).unlink(missing_ok=True)
    for name in PARTS:
        shutil.rmtree(out / name, ignore_errors=True)


def _write_minari(cfg, out: Path) -> None:
    """``format=minari``: the expert's and the behaviour's collections as two Minari datasets under ``out``."""
    from torchrl_wbrm.data.minari_data import delete_minari_datasets, transitions_to_episodes, write_minari_dataset

    check_minari_out(cfg, out)
    task = get_task(cfg.env)
    datasets, behaviour, expert = task.recorded_collections(seed=cfg.seed, storage=cfg.storage)
    sizes = datasets.sizes()
    if behaviour.shape[0] != sizes["transitions"] + sizes["behaviour_samples"] or expert.shape[0] != sizes["expert_samples"]:
        raise RuntimeError(f"The recorded collections ({behaviour.shape[0]} behaviour, {expert.shape[0]} expert "
                           f"steps) are not the sets' {sizes}.")
    kind = cfg.env.kind
    env_kwargs = task.minari_env_kwargs(behaviour)  # a gymnasium id, or (LQR) the spaces only
    ids = minari_ids(cfg)
    replaced = delete_minari_datasets(ids, out) if cfg.overwrite else []
    written = {}
    for part, data, dataset_id in (("expert", expert, ids[0]), ("behaviour", behaviour, ids[1])):
        ds = write_minari_dataset(dataset_id, transitions_to_episodes(data), data_path=out,
                                  algorithm_name=f"torchrl_wbrm {kind} {part} policy, seed {cfg.seed}",
                                  description=f"torchrl_wbrm {cfg.env.name} {part} data (make_dataset, seed "
                                              f"{cfg.seed})",
                                  **env_kwargs)
        written[dataset_id] = (ds.total_episodes, ds.total_steps)
    print(datasets.summary())
    for dataset_id, (episodes, steps) in written.items():
        print(f"Minari dataset {dataset_id}: {episodes} episodes, {steps} steps"
              + (" (replaced the old one: overwrite=true)" if dataset_id in replaced else ""))
    print(f"saved under the Minari data path {out}")


@hydra.main(config_path=str(CONFIG_DIR), config_name="make_dataset", version_base="1.3")
def make_dataset(cfg: DictConfig) -> None:
    """Collect an offline dataset (D, S^b, S^e) with torchrl's Collector, save it and print what it holds."""
    start = time.perf_counter()
    out = Path(cfg.out)
    if not out.is_absolute():
        out = Path(get_original_cwd()) / out
    try:  # every setting and the output, before any collecting: a refusal is one line
        if cfg.format not in ("torchrl", "minari"):
            raise ValueError(f"format={cfg.format!r} is not allowed: choose 'torchrl' or 'minari'.")
        task = get_task(cfg.env)
        if not task.collects_data:
            raise ValueError(f"env={cfg.env.name} (env.kind={cfg.env.kind}) reads its datasets; make_dataset "
                             f"collects the project's own envs.")
        if cfg.format == "torchrl":
            check_torchrl_out(out, cfg.overwrite)
        else:
            check_minari_out(cfg, out)
    except (ValueError, FileExistsError) as err:
        refuse(err, "make_dataset")
    if cfg.format != "torchrl":  # format=minari
        _write_minari(cfg, out)
        print(f"env: {cfg.env.name}  seed: {cfg.seed}  ({time.perf_counter() - start:.1f} s)")
        return
    datasets = task.make_datasets(seed=cfg.seed, storage=cfg.storage)
    replaced = (out / METADATA).is_file()
    if replaced:  # overwrite=true, checked above
        _remove_dataset(out)
    datasets.save(out)
    print(f"env: {cfg.env.name}  seed: {cfg.seed}  ({time.perf_counter() - start:.1f} s)")
    print(datasets.summary())
    if "optimal_return" in datasets.metadata:
        print(f"optimal_return (exact): {datasets.metadata['optimal_return']:.4f}")
    print(f"saved to {out}" + (" (replaced the dataset there: overwrite=true)" if replaced else ""))
