"""The two-stage WBRM trainer used by every recipe: set-up, one loop for both stages, results.

Set-up builds the run's parts from its config (:mod:`torchrl_wbrm.training.parts`): the data, stage 1's
:class:`~torchrl_wbrm.ratio.DensityRatioFitter` (run only for an algo registered with ``fits_ratio`` and a learned
ratio), stage 2's algo (:mod:`torchrl_wbrm.algos`: every baseline is a configuration of this trainer, ``algo=...``)
and the run's evaluations (:mod:`torchrl_wbrm.training.evaluation`); everything env-specific is the env's
:class:`~torchrl_wbrm.tasks.Task`. Between the stages, :meth:`~torchrl_wbrm.ratio.weighting.Weighting.over`
computes ŵ once over D and stores it in stage 2's buffer. Both stages run through one loop (:meth:`_run_stage`):
tqdm progress, logging, evaluation, checkpoints (:mod:`torchrl_wbrm.training.checkpoint`'s format; a resume ends
bit-identical to an uninterrupted run) and the stops (:mod:`torchrl_wbrm.training.stops`). ``q.select`` is
:mod:`torchrl_wbrm.training.selection`'s, ``results.json`` :mod:`torchrl_wbrm.training.run_results`'.
"""
from __future__ import annotations

import copy
import os
from pathlib import Path
from typing import Callable

import torch
from tensordict import TensorDictBase
from tqdm.auto import tqdm

from torchrl_wbrm.data import make_replay_buffer
from torchrl_wbrm.data.sampling import BufferBatches
from torchrl_wbrm.tasks import Task, get_task
from torchrl_wbrm.keys import CHECKPOINT, DENSITY_RATIO, HELD_OUT_LOSS
from torchrl_wbrm.modules.action_scaling import ActionScaling
from torchrl_wbrm.objectives import NonFiniteError
from torchrl_wbrm.ratio import NonFiniteWeightsError, Weighting, WeightsOver
from torchrl_wbrm.training.checkpoint import (checkpoint_state, restore_training_state, set_rng_state, set_seed,
                                              write_checkpoint)
from torchrl_wbrm.training.config import PreparedConfig, WBRMConfig, config_as_dict, prepare_config
from torchrl_wbrm.training.logging import (configure_console, log_scalars, make_logger, progress_postfix,
                                          truncate_csv_logs)
from torchrl_wbrm.training.evaluation import RunEvaluation
from torchrl_wbrm.training.parts import check_d_settings, load_run_data, make_algo, make_ratio_fitter, step_schedulers
from torchrl_wbrm.training.selection import EXPERT_LIKE, Selection, make_criterion
from torchrl_wbrm.training.results import pause_for_test
from torchrl_wbrm.training.run_results import diverged_results, finished_results, write_results
from torchrl_wbrm.training.resume import changed_keys, check_run_request
from torchrl_wbrm.training.rundir import RunDirClaim, check_run_dir, claim_run_dir, default_run_dir
from torchrl_wbrm.training.stops import (FiniteWatch, RunInterrupted, StopNow, StopSignals, TrainingDiverged,
                                         first_non_finite)

__all__ = ["WBRMTrainer"]


class WBRMTrainer:
    """Builds data, networks, losses and optimisers from a :class:`WBRMConfig` and runs the two stages.

    Args:
        cfg: a :class:`WBRMConfig` (or a Hydra ``DictConfig`` of one), or a
            :class:`~torchrl_wbrm.training.config.PreparedConfig` (the config already merged, resolved and validated,
            with its env's task).
        run_dir: where checkpoints, ``results.json`` and plots go. ``None`` (the default): a new dated directory
            under the working directory, as the recipe's: ``outputs/wbrm_offline/<env.name>/<date>_seed<seed>``
            (:func:`~torchrl_wbrm.training.rundir.default_run_dir`). A resume needs the directory it continues.

    Keyword Args:
        logger: a torchrl ``Logger``, ``None`` (no logging), or ``"config"`` (the default): the logger
            ``cfg.logger`` names, made as the recipe makes it (CSV under ``run_dir/logs/`` by default), so a run
            through the API writes the files the recipe writes.
        resume: continue from ``run_dir/checkpoint.pt``.
        progress: show tqdm bars.
        claim: ``run_dir``'s claim, taken already (by the recipe's Hydra callback); ``None``: the trainer claims it.
        evaluation: build the task's evaluator (``False``: no evaluation env or simulation is built, and the trainer
            can value its policy from D alone, :meth:`offline_value`, but not train or evaluate; a run with
            ``ratio.source=exact`` needs the evaluator's exact ratio).

    A trainer claims ``run_dir`` (:func:`~torchrl_wbrm.training.rundir.claim_run_dir`) before it looks into it and
    holds the claim until :meth:`run` ends: a second trainer or recipe run on the same directory, in this process or
    another, is refused (:class:`~torchrl_wbrm.training.rundir.RunDirInUse`). A refused run or resume changes
    nothing on disk (a resume of a directory that does not exist creates none).
    """

    def __init__(self, cfg, run_dir: str | os.PathLike | None = None, *, logger="config", resume: bool = False,
                 progress: bool = True, evaluation: bool = True, claim: RunDirClaim | None = None):
        # merged, resolved and validated once (or by the recipe's Hydra callback, which hands both on); a task holds
        # one run's data, so a prepared task already used by another trainer is built anew
        prepared = cfg if isinstance(cfg, PreparedConfig) else prepare_config(cfg)
        self.cfg: WBRMConfig = prepared.config
        if self.cfg.seeds is not None:  # one trainer is one run: several seeds are run_seeds' (the recipe's seeds=)
            raise ValueError(
                f"seeds={list(self.cfg.seeds)}: a WBRMTrainer trains one run, of cfg.seed; train several seeds with "
                f"torchrl_wbrm.training.seeds.run_seeds(cfg, run_dir) (the recipe's seeds=[...]), or one WBRMTrainer "
                f"per seed with seed=<s> and seeds=None.")
        self.task: Task = prepared.task if prepared.task.datasets is None else get_task(self.cfg.env)
        if run_dir is None:
            if resume:
                raise ValueError("resume=True needs the run directory to continue (run_dir=...).")
            run_dir = default_run_dir(self.cfg)
        self.run_dir = Path(run_dir)
        # before any data are collected: the directory is claimed, then the checkpoint is read and the config
        # compared (resume), or the directory is checked for an earlier run (a new run never overwrites one without
        # overwrite=true); a refusal leaves the disk as it was
        self.resume_changes = {}
        if not resume:
            self.run_dir.mkdir(parents=True, exist_ok=True)
        self._claim, self._resume_sd = check_run_request(self.cfg, self.run_dir, resume=resume,
                                                         claim=claim, task=self.task)
        try:
            self._init(resume, logger, progress, evaluation)
        except BaseException:
            self.release()
            raise

    def release(self) -> None:
        """Release the claim on the run directory (:meth:`run` takes it again)."""
        claim, self._claim = self.__dict__.get("_claim"), None
        if claim is not None:
            claim.release()

    __del__ = release

    def _init(self, resume: bool, logger, progress: bool, evaluation: bool) -> None:
        if resume:
            self.resume_changes = changed_keys(dict(self._resume_sd["config"]), self.config_record())
        else:
            check_run_dir(self.run_dir, overwrite=self.cfg.overwrite)  # overwrite=true: the earlier run's outputs go
        self._stop = None  # StopSignals while run() runs
        self._checkpoint_state: dict | None = None  # the state of the last checkpoint written (all finite)
        self.logger = None if isinstance(logger, str) else logger
        self.progress = progress
        self.device = torch.device(self.cfg.device)
        self.finite_watch = FiniteWatch(self.device)  # the divergence check of each step's figures
        configure_console(self.cfg.verbose)  # library INFO chatter (torchrl's storage lines) only with verbose=true
        if self.cfg.threads:
            torch.set_num_threads(self.cfg.threads)
        set_seed(self.cfg.seed)
        self.history, self.state = [], {"stage": "ratio", "step": 0}
        self._setup(evaluation)
        if resume:
            self._load_checkpoint()
            reevaluated = self.state["stage"] == "done" and any(k.startswith("eval.") for k in self.resume_changes)
            truncate_csv_logs(self.run_dir / "logs", self.state["stage"], self.state["step"], reevaluated=reevaluated)
        if isinstance(logger, str) and logger == "config":  # the recipe's logger (cfg.logger), as the recipe makes it
            self.logger = make_logger(self.cfg.logger, self.run_dir, f"wbrm_{self.cfg.env.name}_seed{self.cfg.seed}",
                                      self.config_record())

    # ------------------------------------------------------------------ setup
    def _setup(self, evaluation: bool) -> None:
        """The run's parts (:mod:`torchrl_wbrm.training.parts`: data, stage 1's fitter, stage 2's algo, the settings'
        checks), its evaluations (the task's evaluator where ``evaluation``) and where its ŵ comes from."""
        data = load_run_data(self.cfg, self.task)
        self.datasets, self.q_train_data, self.q_holdout = data.datasets, data.train, data.holdout
        self.action_spec, self.gamma, self.q_bound = data.action_spec, data.gamma, data.q_bound
        self.data_fingerprint, self.data_seconds = data.fingerprint, data.seconds
        self.ratio_fitter = make_ratio_fitter(self.cfg, data, self.device)
        self.ratio_network = None if self.ratio_fitter is None else self.ratio_fitter.network
        self.algo, self.schedulers = make_algo(self.cfg, self.task, data, self.device)
        self.q_loss, self.actor, self.optimisers = self.algo.loss, self.algo.policy, self.algo.optimisers
        check_d_settings(self.cfg, self.algo, self.q_train_data)
        self.q_buffer, self.selection = None, None  # built after stage 1 (_build_q_buffer), on the data with ŵ
        self.evaluation = RunEvaluation(self.cfg, self.task, self.algo, self.q_train_data, self.q_holdout, self.device,
                                        build=evaluation)
        rc = self.cfg.ratio
        self.weighting = Weighting(
            source=rc.source if self.algo.uses_ratio else "none", network=self.ratio_network,
            true_ratio=self.evaluation.true_ratio, fitter=self.ratio_fitter, relative_beta=rc.relative_beta,
            aggregate=rc.aggregate, temper=rc.temper, clip=rc.clip, mix=rc.mix, self_normalise=rc.self_normalise,
            device=self.device)

    # ------------------------------------------------------------------ the shared loop
    def _run_stage(self, name: str, total_steps: int, step_fn: Callable[[int], dict], *, eval_every: int,
                   eval_fn: Callable[[int], bool | None], until: int | None = None) -> bool:
        """Run ``step_fn`` from the checkpointed step to ``total_steps``; returns ``False`` if stopped by ``until``.

        Every ``logger.log_every`` steps the step's figures are logged; every ``eval_every`` steps ``eval_fn`` runs
        (it returns ``True`` to stop early); every ``checkpoint_every`` steps a checkpoint is written.
        """
        start = self.state["step"]
        pending = self.state.pop("eval_pending", None)  # an evaluation a signal interrupted at this step
        stop = total_steps if until is None else min(total_steps, until)
        log_every, ckpt_every = self.cfg.logger.log_every, self.cfg.checkpoint_every
        # disable=None: a bar on a terminal, none in a log file (sweeps)
        bar = tqdm(total=total_steps, initial=start, desc=name, disable=None if self.progress else True, mininterval=0.5)
        running: dict[str, float] = {}
        finished_early = False
        try:
            if pending == start and start > 0 and self._evaluate_at(name, start, eval_fn):
                finished_early = True
                stop = start
            for step in range(start + 1, stop + 1):
                try:
                    figures = step_fn(step)
                except NonFiniteError as err:  # a network's output turned NaN/inf inside a loss's input checks
                    raise TrainingDiverged(name, step, str(err.key), float("nan")) from err
                read = (step % log_every == 0 or step == stop or step % eval_every == 0 or step == total_steps
                        or bool(ckpt_every and step % ckpt_every == 0)
                        or (self._stop is not None and self._stop.received is not None))
                bad = self.finite_watch(figures, read=read)
                if bad is not None:  # nothing of this step is checkpointed
                    raise TrainingDiverged(name, step, bad[0], bad[1])
                self.state["step"] = step
                if step % log_every == 0 or step == stop:
                    running = {k: float(v) for k, v in figures.items()}
                    if name == "q":
                        self.q_bound.watch(running, step)
                    log_scalars(self.logger, {f"{name}/{k}": v for k, v in running.items()}, step)
                    self.history.append({"stage": f"{name}_train", "step": step, **running})
                    bar.set_postfix_str(progress_postfix(running), refresh=False)  # fits a 120-column line
                if step % eval_every == 0 or step == total_steps:
                    if self._evaluate_at(name, step, eval_fn):
                        finished_early = True
                if ckpt_every and step % ckpt_every == 0 and step != stop:
                    self.save_checkpoint()
                bar.update(1)
                pause_for_test(f"{name}:{step}")  # the kill tests' hook; nothing unless its variable is set
                if self._stop is not None and self._stop.received is not None:
                    self.save_checkpoint()
                    raise RunInterrupted(self._stop.received, name, step, self.run_dir)
                if finished_early:
                    break
        finally:
            bar.close()
        return finished_early or self.state["step"] >= total_steps

    def _evaluate_at(self, name: str, step: int, eval_fn: Callable[[int], bool | None]) -> bool | None:
        """``eval_fn(step)``; a signal during an evaluation stops the run at once (the evaluation changes no training
        state): the checkpoint records the evaluation as pending, and a resumed run does it first."""
        try:
            return eval_fn(step)
        except StopNow as err:
            self.state["eval_pending"] = step
            self.save_checkpoint()
            raise RunInterrupted(err.signum, name, step, self.run_dir, during="evaluation") from None

    # ------------------------------------------------------------------ stage 1
    @torch.no_grad()
    def _ratio_eval(self, step: int) -> bool:
        result = self.ratio_fitter.evaluate(step)
        checked = {HELD_OUT_LOSS: result[HELD_OUT_LOSS]}
        record = {"stage": "ratio", "step": step, **checked, **self.evaluation.ratio_figures(self.ratio_network)}
        self._record(record, "ratio evaluation", "ratio_eval", checked)
        return result["stop"]

    def _record(self, record: dict, what: str, prefix: str, checked: dict) -> None:
        """An evaluation's ``record`` into the history; a non-finite ``checked`` figure stops the run, else logged."""
        self.history.append(record)
        bad = first_non_finite(checked)
        if bad is not None:
            raise TrainingDiverged(what, record["step"], bad[0], bad[1])
        log_scalars(self.logger, {f"{prefix}/{k}": v for k, v in record.items() if isinstance(v, float)}, record["step"])

    # ------------------------------------------------------------------ stage 1's hand-over to stage 2
    def _weights_over(self, data: TensorDictBase, what: str, **kwargs) -> WeightsOver:
        """The run's ``weighting.over(data, **kwargs)``; non-finite weights stop the run, naming ``what``."""
        try:
            return self.weighting.over(data, **kwargs)
        except NonFiniteWeightsError as err:
            raise TrainingDiverged(what, 0, DENSITY_RATIO, err.value) from err

    @torch.no_grad()
    def _build_q_buffer(self, log: bool = True) -> None:
        """Stage 1's hand-over in one call into :mod:`torchrl_wbrm.ratio` (ŵ over D's training rows, stored there,
        the fitter's verdict, D's expert-like episodes where a setting reads them, the figures), then stage 2's
        buffer of those rows and the ``q.select`` criterion on them."""
        self.q_train_weights, self.ratio_check, self.selection, self.weight_stats = None, None, None, {}  # ŵ ≡ 1
        if self.algo.data == "expert":
            self.q_buffer = make_replay_buffer(self.datasets.expert_samples[:], batch_size=self.cfg.q.batch_size)
            return
        qc = self.cfg.q
        over = self._weights_over(
            self.q_train_data.clone(), "weights over D", expert_like=qc.expert_bc_from_d or qc.select in EXPERT_LIKE,
            mark_expert_like=self.algo.marks_expert_like,
            true_expert_episodes=self.datasets.metadata.get("behaviour_expert_episode_ids"))
        self.ratio_check = over.verdict
        if qc.expert_bc_from_d:  # the actor's cloning term: S^e and these episodes
            self.algo.cloning.add_expert_like(over.data[over.expert_like])
        self.q_train_weights = None if self.weighting.source == "none" else over.weights
        d = over.data if self.algo.map_data is None else self.algo.map_data(over.data)
        self.q_buffer = make_replay_buffer(d, batch_size=qc.batch_size)
        if qc.select != "last":
            held_out = lambda: self._weights_over(self.q_holdout.clone(),  # noqa: E731
                                                  "weights over the held-out episodes").weights
            rows = over.data[over.expert_like] if over.expert_like is not None else None
            self.selection = Selection(make_criterion(
                qc.select, held_out_weights=held_out, expert_like_rows=rows, actor=self.actor,
                half_width=ActionScaling(self.action_spec).half_width, loss=self.algo.bellman_loss, gamma=self.gamma,
                device=self.device))
        self.weight_stats = over.figures
        if log:
            log_scalars(self.logger, {f"weights/{k}": v for k, v in self.weight_stats.items()}, 0)

    def offline_value(self, steps: int | None = None) -> tuple[dict, dict]:
        """The current actor's value from D's training episodes alone, without the environment
        (:func:`~torchrl_wbrm.training.offline_value.offline_value_figures`: FQE, and where stage 2 read ŵ, FQE
        weighted as ``eval.offline_value_weights`` says): ``(final figures, record)``. ``steps``: FQE's steps
        (default ``eval.offline_value_steps``). Runs on a forked generator: training draws what it would without it."""
        return self.evaluation.offline_value(self.q_train_weights, self.weighting, steps)

    # ------------------------------------------------------------------ stage 2
    def _q_step(self, step: int) -> dict:
        """One update of the configured algo on one batch of its buffer (then the learning-rate schedules)."""
        figures = self.algo.step(self._q_batches().sample(), step)
        step_schedulers(self.schedulers)
        return figures

    def _q_batches(self) -> BufferBatches:
        """``q_buffer``'s batches as ``q_buffer.sample()`` draws them, gathered into preallocated device tensors."""
        cached = self.__dict__.get("_q_batches_cache")
        if cached is None or cached[0] is not self.q_buffer:
            cached = self._q_batches_cache = (self.q_buffer, BufferBatches(self.q_buffer, device=self.device))
        return cached[1]

    def _q_eval(self, step: int) -> None:
        record = {"stage": "q", "step": step,
                  **self.evaluation.stage_two(step, self.selection, self.history, stop=self._stop)}
        self._record(record, "q evaluation", "eval",
                     {k: v for k, v in record.items() if k != "step" and not k.endswith(("_ci", "_stderr"))})

    def evaluate(self, *, final: bool = False) -> dict:
        """Evaluate the current actor and Q (:meth:`~torchrl_wbrm.training.evaluation.RunEvaluation.evaluate`): a flat
        dict of floats (LQR: regret, return, Q* error, ratio), on a forked global generator."""
        return self.evaluation.evaluate(self.selection, final=final)

    # ------------------------------------------------------------------ run
    def run(self, *, until: int | None = None) -> dict | None:
        """Run (or continue) both stages. ``until``: stop stage 2 after this step (for interruption tests).

        Returns the results dict (also written to ``results.json``; ``"status"`` is ``"finished"``, or
        ``"diverged"`` when a non-finite loss, Q, ratio or parameter stopped the run: the last finite checkpoint is
        kept and ``"diverged"`` names the stage, step and figure), or ``None`` when stopped by ``until``. SIGINT and
        SIGTERM stop it at the next step boundary: a checkpoint is written and :class:`RunInterrupted` raised.
        """
        if self.evaluation.evaluator is None:
            raise ValueError("This trainer was built with evaluation=False: it can value its policy from D "
                             "(offline_value) but not run; build it with evaluation=True to train or evaluate.")
        if self._claim is None:  # released by an earlier run() (e.g. one stopped by ``until``)
            self._claim = claim_run_dir(self.run_dir)
        try:
            with StopSignals() as self._stop:
                return self._run(until=until)
        except TrainingDiverged as err:  # results.json says where (run_results.diverged_results)
            last = self._checkpoint_state or {}
            err.checkpoint_step = last.get("step")
            return write_results(self.run_dir, diverged_results(
                self.cfg, self.history, err, checkpoint_stage=last.get("stage"), data_seconds=self.data_seconds,
                config=self.config_record()), self.history)
        except StopNow as err:  # the re-evaluation of a finished run: its checkpoint is complete, nothing to write
            raise RunInterrupted(err.signum, self.state["stage"], self.state["step"], self.run_dir,
                                 during="evaluation") from None
        finally:
            self._stop = None
            self.release()

    def _run(self, *, until: int | None) -> dict | None:
        if self.state["stage"] == "ratio":
            if self.ratio_fitter is not None:
                self._run_stage("ratio", self.cfg.ratio.steps, lambda step: self.ratio_fitter.step(),
                                eval_every=self.cfg.ratio.eval_every, eval_fn=self._ratio_eval)
                self.ratio_fitter.best_network()  # the best held-out state
            self.state = {"stage": "q", "step": 0}
            self._build_q_buffer()
            self.save_checkpoint()
        if self.q_buffer is None:
            self._build_q_buffer()
        if self.state["stage"] == "done" and self.state["step"] < self.cfg.q.steps:
            self.state["stage"] = "q"  # resumed with a larger budget: continue training
            if self.selection is not None:  # from the last step's parameters, not a selected earlier evaluation's
                self.selection.restore_last(self.q_loss)
        if self.state["stage"] == "q":
            done = self._run_stage("q", self.cfg.q.steps, self._q_step, eval_every=self.cfg.q.eval_every,
                                   eval_fn=self._q_eval, until=until)
            self.save_checkpoint()
            if not done:
                return None
            self.state = {"stage": "done", "step": self.cfg.q.steps}
            self.save_checkpoint()
        elif any(k.startswith("eval.") for k in self.resume_changes):  # a finished run, evaluated anew
            self._q_eval(self.cfg.q.steps)
        return self.results()

    def results(self) -> dict:
        """The finished run's results (:func:`~torchrl_wbrm.training.run_results.finished_results`), written with the
        history, then the plots and the logger's summary."""
        offline_value = self.offline_value() if self.cfg.eval.offline_value else None  # FQE on D: no environment
        results = finished_results(
            self.cfg, self.history, datasets=self.datasets, weights=self.weight_stats, ratio_check=self.ratio_check,
            ratio_source=self.weighting.source, ratio_best=getattr(self.ratio_fitter, "best", None),
            selection_figure=None if self.selection is None else self.selection.figure, offline_value=offline_value,
            bound=self.q_bound, q_mean_data=self.evaluation.q_mean_over_d(), data_seconds=self.data_seconds,
            config=self.config_record())
        title = f"{self.cfg.algo}, {self.cfg.env.name}, seed {self.cfg.seed}" if self.cfg.plots else None
        return write_results(self.run_dir, results, self.history, plots=title, logger=self.logger)

    # ------------------------------------------------------------------ checkpoints
    def config_record(self) -> dict:
        """The run's config as the plain dict saved under ``"config"`` (:func:`config_as_dict`), built once: every
        checkpoint and the results repeat it, and building it merges the schema anew each time."""
        if getattr(self, "_config_record", None) is None:
            self._config_record = config_as_dict(self.cfg, self.task)
        return copy.deepcopy(self._config_record)

    def state_dict(self) -> dict:
        """The checkpoint's content (:func:`~torchrl_wbrm.training.checkpoint.checkpoint_state`)."""
        return checkpoint_state(state=self.state, history=self.history, q_loss=self.q_loss, optimisers=self.optimisers,
                                schedulers=self.schedulers, data_fingerprint=self.data_fingerprint,
                                config=self.config_record(), selection=self.selection,
                                ratio_fitter=self.ratio_fitter)

    def save_checkpoint(self) -> Path:
        """Write ``checkpoint.pt`` (:func:`~torchrl_wbrm.training.checkpoint.write_checkpoint`: atomically, refused
        with :class:`TrainingDiverged` if a parameter is not finite, so the one on disk is always the last finite)."""
        write_checkpoint(self.run_dir / CHECKPOINT, self.state_dict(), claim=self._claim,
                         modules=(self.q_loss, getattr(self.ratio_fitter, "loss_module", None)))
        self._checkpoint_state = dict(self.state)
        return self.run_dir / CHECKPOINT

    def _load_checkpoint(self) -> None:
        """Restore the checkpoint read (and whose config was checked) in ``__init__``
        (:func:`~torchrl_wbrm.training.checkpoint.restore_training_state`), stage 2's buffer, then the random states."""
        sd, self._resume_sd = self._resume_sd, None
        restore_training_state(sd, self.run_dir / CHECKPOINT, data_fingerprint=self.data_fingerprint, q_loss=self.q_loss,
                               optimisers=self.optimisers, schedulers=self.schedulers, ratio_fitter=self.ratio_fitter)
        self.state, self.history = sd["state"], sd["history"]
        self._checkpoint_state = dict(self.state)
        if self.state["stage"] != "ratio":
            self._build_q_buffer(log=False)  # the weights were logged when stage 2 first started
            if self.selection is not None:
                self.selection.best, self.selection.last_state = sd.get("q_best"), sd.get("q_last")
        set_rng_state(sd["rng"])
