"""The two-stage WBRM trainer used by every recipe.

Stage 1 fits ŵ with :class:`~torchrl_wbrm.objectives.RobustDensityRatioLoss` on S^b and S^e, with a held-out split
for early stopping; ŵ is then computed *once* over D and stored in D's replay buffer under ``"density_ratio"``
(optionally shaped and self-normalised), never recomputed per batch. Both are :mod:`torchrl_wbrm.ratio`'s public
pieces (:class:`~torchrl_wbrm.ratio.DensityRatioFitter`, stepped and evaluated from this trainer's loop, and
:func:`~torchrl_wbrm.ratio.weights_over`, the hand-over to stage 2 in one call), which a script can use without a
trainer. Stage 2 trains Q (and the actor) with :class:`~torchrl_wbrm.objectives.WeightedBellmanLoss`, torchrl's
``SoftUpdate`` and periodic evaluation; ``q.select`` is :mod:`torchrl_wbrm.training.selection`'s, the checkpoint
format :mod:`torchrl_wbrm.training.checkpoint`'s and ``results.json`` :mod:`torchrl_wbrm.training.run_results`'.

Baselines are configurations of the same trainer (``algo=...``): :mod:`torchrl_wbrm.algos` (one file per algorithm)
builds each method's loss, optimisers, step function and evaluated policy; stage 1 runs only for an algo registered
with ``fits_ratio`` (``wbrm``; ``bc`` with ``baselines.bc.data=weighted``) and a learned ratio. Everything
env-specific (the data, the action box, γ, the evaluator and the ground truth) is the env's
:class:`~torchrl_wbrm.tasks.Task`: the trainer never asks which env it runs.

Both stages run through one loop (:meth:`WBRMTrainer._run_stage`): tqdm progress with running figures, logging,
evaluation, checkpoints and the stops (divergence, signals, Q's bound: :mod:`torchrl_wbrm.training.stops`); the seeds
of ``seeds=[...]`` run through it one after another (:mod:`torchrl_wbrm.training.seeds`). A checkpoint holds the
models, optimisers, early-stopping state, RNG states, step and history; ``WBRMTrainer(cfg, run_dir, resume=True)``
continues from it and ends bit-identical to an uninterrupted run.
"""
from __future__ import annotations

import copy
import math
import os
import time
import warnings
from pathlib import Path
from typing import Callable

import torch
from tensordict import TensorDictBase
from tqdm.auto import tqdm

from torchrl_wbrm.data import OfflineDatasets, make_replay_buffer
from torchrl_wbrm.data.datasets import split_by_episode
from torchrl_wbrm.data.sampling import BufferBatches, PairedSampler
from torchrl_wbrm.tasks import Evaluator, Task, cached_offline_datasets, get_task
from torchrl_wbrm.evaluation import ratio_error
from torchrl_wbrm.keys import CHECKPOINT, DENSITY_RATIO, EPISODE, HELD_OUT_LOSS, HISTORY, RESULTS
from torchrl_wbrm.modules import DensityRatioNetwork
from torchrl_wbrm.modules.action_scaling import ActionScaling
from torchrl_wbrm.objectives import RobustDensityRatioLoss
from torchrl_wbrm.objectives.functional import bellman_residual
from torchrl_wbrm.ratio import DensityRatioFitter, NonFiniteWeightsError
from torchrl_wbrm.ratio.weighting import WeightsOver, raw_density_ratio, weights_over
from torchrl_wbrm.algos import Algo, AlgoContext, adam_options, build_algo, get_algo
from torchrl_wbrm.training.checkpoint import (checkpoint_state, data_fingerprint, restore_training_state, same_data,
                                              set_rng_state, set_seed, write_checkpoint)
from torchrl_wbrm.training.config import PreparedConfig, WBRMConfig, config_as_dict, prepare_config
from torchrl_wbrm.training.logging import (configure_console, log_run_summary, make_logger, progress_postfix,
                                          truncate_csv_logs)
from torchrl_wbrm.objectives._utils import NonFiniteError
from torchrl_wbrm.training.offline_value import offline_value_figures
from torchrl_wbrm.training.selection import EXPERT_LIKE, Selection, make_criterion
from torchrl_wbrm.training.results import pause_for_test, write_json
from torchrl_wbrm.training.run_results import diverged_results, finished_results
from torchrl_wbrm.training.resume import changed_keys, check_run_request
from torchrl_wbrm.training.rundir import RunDirClaim, check_run_dir, claim_run_dir, unique_dir
from torchrl_wbrm.training.stops import (
    QBound,
    RunInterrupted,
    StopNow,
    StopSignals,
    TrainingDiverged,
    first_non_finite,
    non_finite_parameter,
)

__all__ = ["WBRMTrainer", "default_run_dir"]


def step_schedulers(schedulers: dict) -> None:
    """One step of each learning-rate schedule in ``schedulers`` (an actor updated every k-th step has not stepped
    its optimiser yet at step 1: torch's warning about that order is expected and silenced)."""
    if not schedulers:
        return
    if all(getattr(scheduler, "_step_count", 0) > 1 for scheduler in schedulers.values()):
        for scheduler in schedulers.values():  # torch warns only on a schedule's first step: no filter to set up
            scheduler.step()
        return
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"Detected call of `lr_scheduler\.step\(\)` before")
        for scheduler in schedulers.values():
            scheduler.step()


def default_run_dir(cfg, root: str | os.PathLike = "outputs/wbrm_offline") -> Path:
    """A new run directory named as the recipe names its own, ``<root>/<env.name>/<%Y-%m-%d_%H-%M-%S>_seed<seed>``,
    created with one exclusive ``mkdir`` (``..._1``, ``..._2``, ... when it exists: two runs started in the same
    second get directories of their own)."""
    return unique_dir(Path(root) / cfg.env.name / f"{time.strftime('%Y-%m-%d_%H-%M-%S')}_seed{cfg.seed}")


class WBRMTrainer:
    """Builds data, networks, losses and optimisers from a :class:`WBRMConfig` and runs the two stages.

    Args:
        cfg: a :class:`WBRMConfig` (or a Hydra ``DictConfig`` of one), or a
            :class:`~torchrl_wbrm.training.config.PreparedConfig` (the config already merged, resolved and validated,
            with its env's task).
        run_dir: where checkpoints, ``results.json`` and plots go. ``None`` (the default): a new dated directory
            under the working directory, as the recipe's: ``outputs/wbrm_offline/<env.name>/<date>_seed<seed>``
            (:func:`default_run_dir`). A resume needs the directory it continues.

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
        self._claim: RunDirClaim | None = None
        self.evaluation = evaluation
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
                                                         claim=self._given_claim(claim), task=self.task)
        try:
            self._init(resume, logger, progress)
        except BaseException:
            self.release()
            raise

    def _given_claim(self, claim: RunDirClaim | None) -> RunDirClaim | None:
        """``claim`` where it is a held claim of this run's directory (``None``: none given or no longer held); a claim
        of another directory is refused."""
        if claim is None or not claim.held:
            return None
        if os.path.realpath(claim.path) != os.path.realpath(self.run_dir):
            raise ValueError(f"claim= holds {claim.path}, not this run's directory {self.run_dir}.")
        return claim

    def release(self) -> None:
        """Release the claim on the run directory (:meth:`run` takes it again)."""
        if self._claim is not None:
            self._claim.release()
            self._claim = None

    def __del__(self) -> None:
        if self.__dict__.get("_claim") is not None:
            self.release()

    def _init(self, resume: bool, logger, progress: bool) -> None:
        if resume:
            self.resume_changes = changed_keys(dict(self._resume_sd["config"]), self.config_record())
        else:
            check_run_dir(self.run_dir, overwrite=self.cfg.overwrite)  # overwrite=true: the earlier run's outputs go
        self._stop = None  # StopSignals while run() runs
        self._checkpoint_state: dict | None = None  # the state of the last checkpoint written (all finite)
        self.logger = None if isinstance(logger, str) else logger
        self.progress = progress
        self.device = torch.device(self.cfg.device)
        configure_console(self.cfg.verbose)  # library INFO chatter (torchrl's storage lines) only with verbose=true
        if self.cfg.threads:
            torch.set_num_threads(self.cfg.threads)
        set_seed(self.cfg.seed)
        self.history: list[dict] = []
        self.state = {"stage": "ratio", "step": 0}
        self._setup_data()
        self._setup_ratio()
        self._setup_q()
        self._check_d_settings()
        self._setup_evaluation()
        if resume:
            self._load_checkpoint()
            reevaluated = self.state["stage"] == "done" and any(k.startswith("eval.") for k in self.resume_changes)
            truncate_csv_logs(self.run_dir / "logs", self.state["stage"], self.state["step"], reevaluated=reevaluated)
        if isinstance(logger, str) and logger == "config":  # the recipe's logger (cfg.logger), as the recipe makes it
            self.logger = make_logger(self.cfg.logger, self.run_dir, f"wbrm_{self.cfg.env.name}_seed{self.cfg.seed}",
                                      self.config_record())

    # ------------------------------------------------------------------ setup
    def _check_d_settings(self) -> None:
        """Refuse, in one line and before stage 1, a setting this run cannot carry out after it: ``q.expert_bc_from_d``
        for an algo without the S^e cloning term, and, on data without episode ids (key ``"episode"``), a setting that
        reads D's episodes: ``q.expert_bc_from_d``, an algo that marks D's expert-like episodes,
        ``ratio.aggregate='episode'`` where the algo reads a ratio, and a ``q.select`` on D's expert-like episodes."""
        if self.cfg.q.expert_bc_from_d and self.algo.cloning is None:  # validate_config refuses it for the built-in
            # algos without the S^e cloning term; a custom algo may lack one
            raise ValueError(f"q.expert_bc_from_d=true extends the actor's S^e cloning term, which algo="
                             f"{self.cfg.algo} does not have.")
        if EPISODE in self.q_train_data.keys():
            return
        reads_ratio = self.algo.uses_ratio and self.cfg.ratio.source != "none"
        for needed, setting, instead in (
                (self.cfg.q.expert_bc_from_d, "q.expert_bc_from_d=true", "set q.expert_bc_from_d=false"),
                (self.algo.marks_expert_like, f"algo={self.cfg.algo}'s cloning of D's expert-like episodes",
                 "choose another of its settings"),
                (reads_ratio and self.cfg.ratio.aggregate == "episode", "ratio.aggregate='episode'",
                 "use ratio.aggregate=transition"),
                (self.cfg.q.select in EXPERT_LIKE, f"q.select={self.cfg.q.select}",
                 "use q.select=held_out_weighted_residual")):
            if needed:
                raise ValueError(f"{setting} needs D's episode ids (key 'episode'), which these data do not hold: "
                                 f"{instead}.")

    def _setup_data(self) -> None:
        t0 = time.perf_counter()
        # self.task: everything env-specific (data, action box, γ, evaluator, truth)
        if self.cfg.data_cache:
            self.datasets: OfflineDatasets = cached_offline_datasets(self.cfg.env, seed=self.cfg.seed, cache_dir=self.cfg.data_cache)
        else:
            self.datasets = self.task.make_datasets(seed=self.cfg.seed)
        self.task.attach(self.datasets)
        self.data_seconds = time.perf_counter() - t0 + self.task.check_seconds  # the checks' read of the data too
        d = self.datasets.transitions[:]
        gen = torch.Generator().manual_seed(self.cfg.seed + 23)
        self.q_train_data, self.q_holdout = split_by_episode(d, self.cfg.q.holdout_fraction, generator=gen)
        self.observation_dim = d["observation"].shape[-1]
        self.action_dim = d["action"].shape[-1]
        self.action_spec = self.task.action_spec()
        self.gamma = self.task.gamma(self.cfg.q.gamma)
        self.q_bound = QBound(float(d["next", "reward"].abs().max()), self.gamma)  # Q's scale: the run's one rule
        # the SHA-256 of every tensor of D, S^b and S^e: a resume on different data is refused
        self.data_fingerprint = data_fingerprint(self.datasets)

    def _setup_ratio(self) -> None:
        rc = self.cfg.ratio
        self.ratio_network = None
        self.ratio_fitter: DensityRatioFitter | None = None
        if rc.source != "learned" or not get_algo(self.cfg.algo).fits_ratio_for(self.cfg):
            return
        self.ratio_network = DensityRatioNetwork(
            self.observation_dim,
            self.action_dim,
            bounds=tuple(rc.bounds),
            parameterisation=rc.parameterisation,
            num_cells=rc.num_cells,
            activation=rc.activation,
            layer_norm=rc.layer_norm,
        ).to(self.device)
        ratio_loss = RobustDensityRatioLoss(
            self.ratio_network,
            alpha="kl" if rc.divergence == "kl" else rc.alpha,
            normalisation_coefficient=rc.normalisation_coefficient,
            non_negative_correction=rc.non_negative_correction,
            relative_beta=rc.relative_beta,
        )
        ratio_params = list(ratio_loss.parameters())
        optimiser = torch.optim.Adam(ratio_params, lr=rc.lr, weight_decay=rc.weight_decay, **adam_options(ratio_params))
        # stage 1 is torchrl_wbrm.ratio's fitter (held-out split of S^b and S^e, best state, patience), stepped and
        # evaluated from this trainer's loop
        self.ratio_fitter = DensityRatioFitter(
            ratio_loss, self.datasets.behaviour_samples, self.datasets.expert_samples, batch_size=rc.batch_size,
            optimizer=optimiser, grad_clip=rc.grad_clip, holdout_fraction=rc.holdout_fraction,
            generator=torch.Generator().manual_seed(self.cfg.seed + 17), patience=rc.patience, device=self.device,
        )
        # the fitter's paired batches, gathered straight into preallocated tensors on the device
        self.ratio_batches = PairedSampler(self.ratio_fitter.behaviour_buffer, self.ratio_fitter.expert_buffer,
                                           rc.batch_size, device=self.device)
        self.ratio_fitter.sampler = self.ratio_batches

    def _setup_q(self) -> None:
        """Stage 2 (or the baseline named by ``algo``): loss, optimisers, step function and evaluated policy."""
        qc = self.cfg.q
        d = self.datasets.transitions[:]
        init_bias = d["next", "reward"].mean().item() / (1 - self.gamma) if qc.init_bias else 0.0
        loc = scale = None
        if qc.normalise_observations:  # D's statistics, a fixed input layer of every network
            observations = self.q_train_data["observation"].double()
            loc, scale = observations.mean(0).float(), observations.std(0).clamp_min(1e-6).float()
        context = AlgoContext(
            cfg=self.cfg,
            observation_dim=self.observation_dim,
            action_dim=self.action_dim,
            action_spec=self.action_spec,
            gamma=self.gamma,
            q_initial_bias=init_bias,
            device=self.device,
            observation_loc=loc,
            observation_scale=scale,
            task=self.task,
        )
        self.algo: Algo = build_algo(self.cfg.algo, context)
        self.schedulers = {}
        if qc.lr_schedule == "cosine":  # every optimiser annealed over the step budget, stepped once per trainer step
            self.schedulers = {name: torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, T_max=qc.steps)
                               for name, optimiser in self.algo.optimisers.items()}
        self.q_loss = self.algo.loss
        self.actor = self.algo.policy  # the policy evaluated (deterministic mode)
        self.optimisers = self.algo.optimisers
        self.q_buffer = None  # built after stage 1, with the weights in it
        if qc.select != "last" and self.algo.bellman_loss is None:
            raise ValueError(f"q.select={qc.select} chooses by the held-out Bellman residual, which "
                             f"algo={self.cfg.algo} does not fit: use q.select=last or an algo with one "
                             f"(wbrm, brm, fqi, mabo).")
        # q.select other than last: its criterion and best-so-far (training/selection.py), built on the data with
        # the weights, in _build_q_buffer
        self.selection: Selection | None = None

    def _setup_evaluation(self) -> None:
        """The task's evaluator: its evaluation samples (where Q* is known) and the exact ratio (where known)."""
        if not self.evaluation:
            if self.cfg.ratio.source == "exact" and self.algo.uses_ratio:
                raise ValueError("evaluation=False builds no evaluator, and ratio.source=exact reads the evaluator's "
                                 "exact ratio: build the trainer with evaluation=True.")
            self.evaluator, self.eval_samples, self.true_ratio = None, {}, None
            return
        self.evaluator: Evaluator = self.task.evaluator(self.cfg.eval)
        self.eval_samples = self.evaluator.eval_samples
        self.true_ratio = self.evaluator.true_ratio

    # ------------------------------------------------------------------ the shared loop
    def _run_stage(
        self,
        name: str,
        total_steps: int,
        step_fn: Callable[[int], dict],
        *,
        eval_every: int,
        eval_fn: Callable[[int], bool | None],
        until: int | None = None,
    ) -> bool:
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
                bad = self._non_finite_figure(figures, read=read)
                if bad is not None:  # nothing of this step is checkpointed
                    raise TrainingDiverged(name, step, bad[0], bad[1])
                self.state["step"] = step
                if step % log_every == 0 or step == stop:
                    running = {k: float(v) for k, v in figures.items()}
                    if name == "q":
                        self.q_bound.watch(running, step)
                    self._log({f"{name}/{k}": v for k, v in running.items()}, step)
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

    def _non_finite_figure(self, figures: dict, *, read: bool) -> tuple[str, float] | None:
        """The divergence check of a step's figures: :func:`first_non_finite` on CPU (a host read costs nothing
        there). On an accelerator a device-side "all finite so far" flag is accumulated without a host sync and read
        (one sync) only when ``read`` (log, evaluation and checkpoint steps, the last step, a stop signal), so a
        divergence is caught at the next such step, before anything after it is logged or checkpointed; it names
        that step's first non-finite figure (a NaN persists), or the window's if they are finite again."""
        if self.device.type == "cpu":
            return first_non_finite(figures)
        values = [v.detach().reshape(()).float() for v in figures.values()
                  if isinstance(v, torch.Tensor) and v.numel() == 1 and (v.is_floating_point() or v.is_complex())]
        flag = self.__dict__.get("_finite_flag")
        if values:
            ok = torch.isfinite(torch.stack(values)).all()
            flag = ok if flag is None else flag & ok
        self._finite_flag = flag
        if not read or flag is None:
            return None
        self._finite_flag = None
        if bool(flag):
            return None
        return first_non_finite(figures) or ("a figure of the steps since the last check", float("nan"))

    def _log(self, scalars: dict[str, float], step: int) -> None:
        if self.logger is not None:
            for k, v in scalars.items():
                if v is not None and math.isfinite(v):
                    self.logger.log_scalar(k, v, step=step)

    # ------------------------------------------------------------------ stage 1
    def _ratio_step(self, step: int) -> dict:
        return self.ratio_fitter.step()

    @torch.no_grad()
    def _ratio_eval(self, step: int) -> bool:
        result = self.ratio_fitter.evaluate(step)
        held_out = result[HELD_OUT_LOSS]
        record = {"stage": "ratio", "step": step, HELD_OUT_LOSS: held_out}
        record.update(self._ratio_truth_figures())
        self.history.append(record)
        if not math.isfinite(held_out):
            raise TrainingDiverged("ratio evaluation", step, HELD_OUT_LOSS, held_out)
        self._log({f"ratio_eval/{k}": v for k, v in record.items() if isinstance(v, float)}, step)
        return result["stop"]

    @torch.no_grad()
    def _ratio_truth_figures(self) -> dict:
        if self.true_ratio is None or self.ratio_network is None:
            return {}
        b = self.eval_samples["behaviour"].to(self.device)
        w_hat = self.ratio_network(b.clone())[DENSITY_RATIO]
        w = self.true_ratio(b.clone())[DENSITY_RATIO]
        return {f"ratio_{k}": v for k, v in ratio_error(w_hat, w).items()}

    # ------------------------------------------------------------------ weights over D
    def _weights_over(self, data: TensorDictBase, source: str, what: str, **kwargs) -> WeightsOver:
        """:func:`~torchrl_wbrm.ratio.weights_over` with the run's ratio settings; non-finite weights stop the run,
        naming ``what``."""
        rc = self.cfg.ratio
        try:
            return weights_over(data, source=source, network=self.ratio_network, true_ratio=self.true_ratio,
                                relative_beta=rc.relative_beta, aggregate=rc.aggregate, temper=rc.temper,
                                clip=rc.clip, mix=rc.mix, self_normalise=rc.self_normalise, device=self.device,
                                **kwargs)
        except NonFiniteWeightsError as err:
            raise TrainingDiverged(what, 0, DENSITY_RATIO, err.value) from err

    def _raw_weights(self, d: TensorDictBase, source: str) -> torch.Tensor:
        """ŵ over the rows of ``d`` before any shaping (:func:`~torchrl_wbrm.ratio.raw_density_ratio`)."""
        return raw_density_ratio(d, source=source, network=self.ratio_network, true_ratio=self.true_ratio,
                                 relative_beta=self.cfg.ratio.relative_beta, device=self.device)

    @torch.no_grad()
    def _build_q_buffer(self) -> None:
        """Stage 1's hand-over: ŵ over D's training rows, stored in stage 2's buffer (one call into
        :mod:`torchrl_wbrm.ratio`), the fitter's verdict, D's expert-like episodes where a setting reads them, and
        the ``q.select`` criterion on those data."""
        self.q_train_weights = None  # the weights stage 2 gave D's training rows (None: ŵ ≡ 1)
        self.ratio_check = None
        self.selection = None
        if self.algo.data == "expert":
            self.q_buffer = make_replay_buffer(self.datasets.expert_samples[:], batch_size=self.cfg.q.batch_size)
            self.weight_stats = {}
            return
        qc = self.cfg.q
        source = self.cfg.ratio.source if self.algo.uses_ratio else "none"
        over = self._weights_over(
            self.q_train_data.clone(), source, "weights over D", fitter=self.ratio_fitter,
            expert_like=qc.expert_bc_from_d or qc.select in EXPERT_LIKE, mark_expert_like=self.algo.marks_expert_like,
            true_expert_episodes=self.datasets.metadata.get("behaviour_expert_episode_ids"))
        self.ratio_check = over.verdict
        if qc.expert_bc_from_d:  # the actor's cloning term: S^e and these episodes
            self.algo.cloning.add_expert_like(over.data[over.expert_like])
        self.q_train_weights = None if source == "none" else over.weights
        d = over.data if self.algo.map_data is None else self.algo.map_data(over.data)
        self.q_buffer = make_replay_buffer(d, batch_size=qc.batch_size)
        if qc.select != "last":
            held_out = lambda: self._weights_over(self.q_holdout.clone(), source,  # noqa: E731
                                                  "weights over the held-out episodes").weights
            rows = over.data[over.expert_like] if over.expert_like is not None else None
            self.selection = Selection(make_criterion(
                qc.select, held_out_weights=held_out, expert_like_rows=rows, actor=self.actor,
                half_width=ActionScaling(self.action_spec).half_width, loss=self.algo.bellman_loss, gamma=self.gamma,
                device=self.device))
        self.weight_stats = over.figures
        self._log({f"weights/{k}": v for k, v in self.weight_stats.items()}, 0)

    def offline_value(self, steps: int | None = None) -> tuple[dict, dict]:
        """The current actor's value from D's training episodes alone, without the environment
        (:func:`~torchrl_wbrm.training.offline_value.offline_value_figures`: FQE, and where stage 2 read ŵ, FQE
        weighted as ``eval.offline_value_weights`` says): ``(final figures, record)``. ``steps``: FQE's steps
        (default ``eval.offline_value_steps``). Runs on a forked generator: training draws what it would without it."""
        weights = self.q_train_weights
        if weights is not None and self.cfg.eval.offline_value_weights == "ratio":  # ŵ before any shaping
            w = self._raw_weights(self.q_train_data, self.cfg.ratio.source).reshape(-1, 1).double()
            weights = (w / w.mean()).to(self.q_train_weights.dtype)
        with torch.random.fork_rng():
            figures, record = offline_value_figures(
                self.actor, self.q_train_data, self.task.return_quantity(), weights=weights,
                steps=steps or self.cfg.eval.offline_value_steps, seed=self.cfg.seed)
        record["weights"] = None if weights is None else self.cfg.eval.offline_value_weights
        return figures, record

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
        final = step == self.cfg.q.steps
        selection = self.selection
        if selection is not None and final and selection.last_state is None:
            selection.keep_if_best(step, self._selection_figures()[selection.figure], self.q_loss)
            if selection.best["step"] != step:  # an earlier evaluation's parameters are delivered and scored
                self.history.append({"stage": "q_last", "step": step, **self.evaluate()})  # for "selection"
                selection.deliver(self.q_loss)
        try:
            if self._stop is not None:  # a signal stops a (long) evaluation at once: StopNow
                with self._stop.immediately():
                    figures = self.evaluate(final=final)
            else:
                figures = self.evaluate(final=final)
        except BaseException:
            if selection is not None and final:  # checkpointed as it was trained: the resumed evaluation selects again
                selection.restore_last(self.q_loss)
            raise
        if selection is not None and not final:
            selection.keep_if_best(step, figures.get(selection.figure), self.q_loss)
        if selection is not None and final:
            figures["selected_step"] = selection.best["step"]
        record = {"stage": "q", "step": step, **figures}
        self.history.append(record)
        bad = first_non_finite({k: v for k, v in record.items() if k != "step" and not k.endswith(("_ci", "_stderr"))})
        if bad is not None:
            raise TrainingDiverged("q evaluation", step, bad[0], bad[1])
        self._log({f"eval/{k}": v for k, v in record.items() if isinstance(v, float)}, step)
        return None

    @torch.no_grad()
    def evaluate(self, *, final: bool = False) -> dict:
        """Evaluate the current actor and Q: flat dict of floats (LQR: regret, return, Q* error, ratio).

        Runs on a forked global generator, so evaluating never changes what training draws next.
        """
        with torch.random.fork_rng():
            return self._evaluate(final=final)

    def _evaluate(self, *, final: bool) -> dict:
        ec = self.cfg.eval
        episodes = ec.episodes if final else ec.train_episodes
        self.actor.eval()
        try:
            out = self.evaluator.evaluate(self.actor, episodes=episodes, seed=ec.seed, q_value=self.algo.q_value,
                                          device=self.device)
            if self.algo.bellman_loss is not None:
                out.update(self._selection_figures())
        finally:
            self.actor.train()
        return out

    @torch.no_grad()
    def _selection_figures(self) -> dict[str, float]:
        """The current Q's figures that ``q.select`` can minimise: ``"held_out_bellman_residual"``, the mean δ² (any
        residual form) on the held-out D episodes, and the figure of the run's ``q.select`` criterion
        (:mod:`torchrl_wbrm.training.selection`)."""
        held_out = self.q_holdout.clone().set(DENSITY_RATIO, torch.ones(self.q_holdout.shape[0], 1))
        squared = bellman_residual(*self.algo.bellman_loss.bellman_error(held_out.to(self.device))).pow(2)
        out = {"held_out_bellman_residual": squared.mean().item()}
        if self.selection is not None:
            out[self.selection.figure] = self.selection.criterion.score(squared)
        return out

    # ------------------------------------------------------------------ run
    def run(self, *, until: int | None = None) -> dict | None:
        """Run (or continue) both stages. ``until``: stop stage 2 after this step (for interruption tests).

        Returns the results dict (also written to ``results.json``; ``"status"`` is ``"finished"``, or
        ``"diverged"`` when a non-finite loss, Q, ratio or parameter stopped the run: the last finite checkpoint is
        kept and ``"diverged"`` names the stage, step and figure), or ``None`` when stopped by ``until``. SIGINT and
        SIGTERM stop it at the next step boundary: a checkpoint is written and :class:`RunInterrupted` raised.
        """
        if not self.evaluation:
            raise ValueError("This trainer was built with evaluation=False: it can value its policy from D "
                             "(offline_value) but not run; build it with evaluation=True to train or evaluate.")
        if self._claim is None:  # released by an earlier run() (e.g. one stopped by ``until``)
            self._claim = claim_run_dir(self.run_dir)
        try:
            with StopSignals() as self._stop:
                return self._run(until=until)
        except TrainingDiverged as err:
            err.checkpoint_step = None if self._checkpoint_state is None else self._checkpoint_state["step"]
            return self._diverged_results(err)
        except StopNow as err:  # the re-evaluation of a finished run: its checkpoint is complete, nothing to write
            raise RunInterrupted(err.signum, self.state["stage"], self.state["step"], self.run_dir,
                                 during="evaluation") from None
        finally:
            self._stop = None
            self.release()

    def _run(self, *, until: int | None) -> dict | None:
        if self.state["stage"] == "ratio":
            if self.ratio_network is not None:
                self._run_stage(
                    "ratio", self.cfg.ratio.steps, self._ratio_step,
                    eval_every=self.cfg.ratio.eval_every, eval_fn=self._ratio_eval,
                )
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
            done = self._run_stage(
                "q", self.cfg.q.steps, self._q_step, eval_every=self.cfg.q.eval_every, eval_fn=self._q_eval, until=until
            )
            self.save_checkpoint()
            if not done:
                return None
            self.state = {"stage": "done", "step": self.cfg.q.steps}
            self.save_checkpoint()
        elif any(k.startswith("eval.") for k in self.resume_changes):  # a finished run, evaluated anew
            self._q_eval(self.cfg.q.steps)
        return self.results()

    @torch.no_grad()
    def _q_mean_over_d(self, chunk: int = 8192) -> float:
        """The current Q̂'s mean over D's training rows (its own state-actions), by the algo's ``q_value``."""
        d = self.q_train_data
        total = sum(float(self.algo.q_value(rows.to(self.device))[0].double().sum()) for rows in d.split(chunk))
        return total / d.shape[0]

    def _diverged_results(self, err: TrainingDiverged) -> dict:
        """``results.json`` of a run stopped by divergence (:func:`~torchrl_wbrm.training.run_results.diverged_results`),
        written with the history."""
        results = diverged_results(
            self.cfg, self.history, err, data_seconds=self.data_seconds, config=self.config_record(),
            checkpoint_stage=None if self._checkpoint_state is None else self._checkpoint_state["stage"])
        write_json(self.run_dir / RESULTS, results)
        write_json(self.run_dir / HISTORY, self.history)
        return results

    def results(self) -> dict:
        """The finished run's results (:func:`~torchrl_wbrm.training.run_results.finished_results`), written with the
        history, then the plots and the logger's summary."""
        offline_value = self.offline_value() if self.cfg.eval.offline_value else None  # FQE on D: no environment
        q_mean_data = self._q_mean_over_d() if self.algo.q_value is not None and self.algo.data != "expert" else None
        results = finished_results(
            self.cfg, self.history, datasets=self.datasets, weights=self.weight_stats,
            ratio_source=self.cfg.ratio.source if self.algo.uses_ratio else "none",
            ratio_best=self.ratio_fitter.best if self.ratio_network is not None else None,
            ratio_check=getattr(self, "ratio_check", None),
            selection_figure=None if self.selection is None else self.selection.figure, offline_value=offline_value,
            bound=self.q_bound, q_mean_data=q_mean_data, data_seconds=self.data_seconds, config=self.config_record())
        # the figures are on disk before any plot is drawn: a failing plot cannot lose them
        write_json(self.run_dir / RESULTS, results)
        write_json(self.run_dir / HISTORY, self.history)
        if self.cfg.plots:
            from torchrl_wbrm.training.plots import plot_run

            plot_run(self.history, self.run_dir, title=f"{self.cfg.algo}, {self.cfg.env.name}, seed {self.cfg.seed}",
                     algo=self.cfg.algo, data=results.get("data"))
        if self.logger is not None:  # wandb: final figures with CIs in the summary, plots, a results table
            log_run_summary(self.logger, results, self.run_dir)
        return results

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
                                ratio_fitter=self.ratio_fitter if self.ratio_network is not None else None)

    def save_checkpoint(self) -> Path:
        """Write ``checkpoint.pt`` atomically; refused (:class:`TrainingDiverged`) if a parameter is not finite, so
        the checkpoint on disk is always the last finite one."""
        path = self.run_dir / CHECKPOINT
        bad = non_finite_parameter(self.q_loss, self.ratio_fitter.loss_module if self.ratio_fitter is not None else None)
        if bad is not None:
            raise TrainingDiverged(self.state["stage"], self.state["step"], f"parameter {bad}", float("nan"))
        state = self.state_dict()
        if self._claim is not None:  # the directory this run claimed, not one made anew under its name
            self._claim.check_present()
        write_checkpoint(path, state)
        self._checkpoint_state = dict(self.state)
        return path

    def _load_checkpoint(self) -> None:
        """Restore the checkpoint read (and whose config was checked) in ``__init__``."""
        path = self.run_dir / CHECKPOINT
        sd = self._resume_sd
        if not same_data(sd["data_fingerprint"], self.datasets, self.data_fingerprint):
            raise ValueError(
                f"Cannot resume from {path}: its data differ from the data this config reads now (the SHA-256 of "
                f"every tensor of D, S^b and S^e differs: the dataset's files changed, or the env or seed); a resume "
                f"never mixes two datasets. Start a new run on these data."
            )
        self.state = sd["state"]
        self.history = sd["history"]
        self._checkpoint_state = dict(self.state)
        restore_training_state(sd, q_loss=self.q_loss, optimisers=self.optimisers, schedulers=self.schedulers,
                               ratio_fitter=self.ratio_fitter if self.ratio_network is not None else None)
        if self.state["stage"] != "ratio":
            logger, self.logger = self.logger, None  # the weights were logged when stage 2 first started
            try:
                self._build_q_buffer()
            finally:
                self.logger = logger
            if self.selection is not None:
                self.selection.best, self.selection.last_state = sd.get("q_best"), sd.get("q_last")
        set_rng_state(sd["rng"])
        self._resume_sd = None  # restored: free the copy
