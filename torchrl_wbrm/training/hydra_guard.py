"""The recipes' Hydra callback, :class:`RunDirGuard`: the config, the data, the run directory and a resume are checked
(and the directory claimed) before Hydra writes its ``.hydra/`` record, so a refused command changes nothing on disk.
"""
from __future__ import annotations

import time
import traceback
from pathlib import Path

from hydra.experimental.callback import Callback
from omegaconf import OmegaConf, open_dict, read_write
from omegaconf.errors import OmegaConfBaseException

from torchrl_wbrm.training.config import PreparedConfig, merge_config, prepare_config
from torchrl_wbrm.training.resume import check_run_request
from torchrl_wbrm.training.rundir import (
    RunDirClaim,
    claim_run_dir,
    clear_run_outputs,
    holds_run,
    remove_empty,
    unique_dir,
)

__all__ = ["RunDirGuard"]


class RunDirGuard(Callback):
    """The recipes' Hydra callback (``hydra.callbacks.run_dir_guard``): a run request is checked before Hydra writes
    anything, so a refused command leaves the disk as it was (no ``.hydra/`` record rewritten, no empty dated
    directory under ``outputs/``).

    In ``on_run_start`` (before Hydra creates the run directory and writes ``.hydra/``):

    * the config is merged, resolved and validated, and its env's task built, once
      (:func:`~torchrl_wbrm.training.config.prepare_config`); in ``on_job_start`` the guard hands both, with the
      run directory's claim, to the task function when it takes them (its ``take_prepared(prepared, claim)``,
      :class:`~torchrl_wbrm.cli.RecipeRun`'s);
    * the data on disk it names are read and checked (:meth:`~torchrl_wbrm.tasks.Task.check_data`: a Minari
      pair, or a saved dataset), and held for the run's trainer, which does not read them again;
    * ``resume=X``: Hydra's run directory becomes ``X`` (its record goes with the run it continues), ``X`` must hold
      a checkpoint whose config this one may continue, and ``X`` is claimed;
    * a new run: the default dated directory is created with an exclusive ``mkdir`` (``_1``, ``_2``, ... when two
      runs start in the same second), a given ``hydra.run.dir`` is claimed and must not hold a run unless
      ``overwrite=true``, which then removes the earlier run's outputs, its Hydra record and Hydra's job log
      (``<job name>.log``), nothing else;
    * a directory where something the run writes into (``.hydra/``, ``logs/``, ...) is a symbolic link is refused.

    The claim goes with the prepared config to the task function, which passes it to the run's
    :class:`~torchrl_wbrm.training.WBRMTrainer` (``claim=``); the trainer holds it until the run ends. A refusal exits (``SystemExit``, status 1) with the reason in one line, and with the
    traceback before it only under ``verbose=true``; Hydra would only warn about an exception raised by a callback.
    """

    def __init__(self) -> None:
        self._prepared: PreparedConfig | None = None  # from on_run_start to this run's on_job_start
        self._claim: RunDirClaim | None = None

    def on_run_start(self, config, **kwargs) -> None:
        try:
            self._prepared, self._claim = self.checked(config)
        except (ValueError, TypeError, KeyError, OSError, RuntimeError, OmegaConfBaseException) as err:
            if _verbose(config):
                traceback.print_exc()
            reason = " ".join(str(err).split()) or type(err).__name__  # one line
            raise SystemExit(f"Refused (nothing was written): {reason}") from err

    def on_job_start(self, config, *, task_function, **kwargs) -> None:
        """Hand the config prepared in :meth:`on_run_start` and the claim to the task function, when it takes them."""
        prepared, claim, self._prepared, self._claim = self._prepared, self._claim, None, None
        take = getattr(task_function, "take_prepared", None)
        if prepared is not None and take is not None:
            take(prepared, claim)
        elif claim is not None:  # a task function that takes no claim claims its directory itself
            claim.release()

    @staticmethod
    def check(config) -> RunDirClaim:
        """The checks of :meth:`on_run_start` on a composed config (with its ``hydra`` node); returns the claim."""
        return RunDirGuard.checked(config)[1]

    @staticmethod
    def checked(config) -> tuple[PreparedConfig, RunDirClaim]:
        """:meth:`check`, returning the prepared config too."""
        prepared = prepare_config(_task_config(config))
        cfg, task = prepared
        start = time.perf_counter()
        task.check_data()  # bad data are refused here, before anything is written (and held for the run)
        task.check_seconds = time.perf_counter() - start
        raw_dir = OmegaConf.to_container(config.hydra.run, resolve=False)["dir"]
        dated = isinstance(raw_dir, str) and "${now:" in raw_dir
        if cfg.resume:
            run_dir = Path(cfg.resume)
            given = Path(str(config.hydra.run.dir))
            if not dated and given.resolve() != run_dir.resolve():
                raise ValueError(
                    f"resume={cfg.resume} continues the run in {run_dir}, but hydra.run.dir={given} would put this "
                    f"command's Hydra record elsewhere; drop hydra.run.dir (a resume runs in its own directory)."
                )
            claim, _ = check_run_request(cfg, run_dir, resume=True, task=task)
        else:
            run_dir = Path(str(config.hydra.run.dir))
            if dated:  # a fresh directory of its own, even for two runs started in the same second
                run_dir = unique_dir(run_dir)
                claim = claim_run_dir(run_dir)
            else:
                run_dir.parent.mkdir(parents=True, exist_ok=True)
                try:  # created by this run's own mkdir, not judged by an earlier look: a run started beside it may
                    run_dir.mkdir()  # have made and claimed it in between, and its directory is never removed here
                    created = True
                except FileExistsError:
                    created = False
                try:
                    claim, _ = check_run_request(cfg, run_dir, resume=False, task=task)
                except BaseException:
                    if created:
                        remove_empty(run_dir)
                    raise
                if cfg.overwrite and holds_run(run_dir):  # the earlier run goes, its record and Hydra's job log too
                    clear_run_outputs(run_dir, hydra_record=True, job_name=_job_name(config))
        _set_run_dir(config, run_dir)
        return prepared, claim


def _task_config(config):
    """The run's own config (without the ``hydra`` node) as a :class:`~torchrl_wbrm.training.config.WBRMConfig`."""
    task = OmegaConf.masked_copy(config, [k for k in config.keys() if k != "hydra"])
    return merge_config(task)


def _set_run_dir(config, run_dir: Path) -> None:
    with read_write(config.hydra), open_dict(config.hydra):
        config.hydra.run.dir = str(run_dir)


def _job_name(config) -> str | None:
    """Hydra's job name (its job log is ``<job name>.log``), or ``None`` where the config does not say."""
    name = OmegaConf.select(config, "hydra.job.name", default=None)
    return str(name) if name else None


def _verbose(config) -> bool:
    """The composed config's ``verbose`` setting (``False`` where it cannot be read)."""
    try:
        return OmegaConf.select(config, "verbose", default=False) is True
    except Exception:  # noqa: BLE001 (a config too broken to read: no traceback)
        return False
