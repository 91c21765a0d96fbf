"""Several seeds of one configuration, trained together in one process: ``python recipes/wbrm_offline.py seeds=[0,1,2]``.

Each seed is a :class:`~torchrl_wbrm.training.trainer.WBRMTrainer` of its own (``<run dir>/seed<s>``, built with
``seed=s``): its data, its networks' initialisation, its evaluator and its results are those of a separate run with
that seed. What is shared is the update. For ``wbrm``, ``brm`` and ``fqi`` (continuous actions, ``q.maximiser=actor``)
:class:`SeedGroup` stacks the seeds' parameters (``torch.stack`` of each loss's parameter TensorDicts, leading
dimension = the seeds, as torchrl's ensembles stack theirs) and runs both stages as one :func:`torch.vmap` over the
seeds:

- stage 1: the ratio loss's own network call (``RobustDensityRatioLoss._network_call``) and
  :func:`~torchrl_wbrm.objectives.functional.basu_power_divergence`, one Adam over the stacked parameters, a
  per-seed gradient-norm clip; every ``ratio.eval_every`` steps each seed's fitter scores its held-out sets, keeps
  its best state and counts its patience (a seed that has stopped keeps its best state; the others go on);
- stage 2: :class:`~torchrl_wbrm.objectives.WeightedBellmanLoss`'s own methods (``_chosen_q``,
  ``next_state_value``, ``_target``, ``_weight``, ``actor_loss``) called inside the vmap with each seed's
  parameters swapped in, and :func:`~torchrl_wbrm.objectives.functional.weighted_bellman_residual`; one Adam per
  network over the stacked parameters (Adam is elementwise: the same update as one Adam per seed), the targets
  updated as torchrl's ``SoftUpdate`` / ``HardUpdate`` update them, the learning-rate schedules stepped once per step.

Each seed draws its batches from a generator of its own, started from the global state its setup left, so it
draws what a separate run would draw from the global generator. Every evaluation copies each seed's slice of the
stacked parameters into that seed's trainer and evaluates it there (:meth:`WBRMTrainer._q_eval`), so the figures,
the history and ``results.json`` of a seed are written by the trainer exactly as in a separate run. A seed that
diverges is recorded as diverged (its ``results.json`` says where) and the others go on.

Other algorithms, and settings the vectorised step does not cover (:func:`not_vectorised`), train the seeds one at a
time in the same process (each seed checkpoints as a separate run does). A multi-seed run is resumed
(``resume=<run dir>``, :func:`run_seeds`' ``resume``) seed by seed: finished seeds are kept, a seed with a
checkpoint continues from it, the others run anew.

The run directory's ``results.json`` holds every seed's results under ``"runs"`` and the aggregate over the seeds
(mean and 95% Student-t interval of each final figure, :func:`~torchrl_wbrm.evaluation.stats.mean_ci`) under
``"aggregate"``; :func:`~torchrl_wbrm.training.reporting.load_results` reads it as the seeds' runs.
"""
from __future__ import annotations

import math
import time
from contextlib import contextmanager
from pathlib import Path

import torch
from omegaconf import OmegaConf
from tensordict import TensorDict, TensorDictBase

from torchrl_wbrm.algos import adam_options
from torchrl_wbrm.data.sampling import BufferBatches
from torchrl_wbrm.evaluation.stats import mean_ci
from torchrl_wbrm.objectives import basu_power_divergence, weighted_bellman_residual
from torchrl_wbrm.objectives._utils import per_sample
from torchrl_wbrm.objectives.functional import bellman_residual, effective_sample_size
from torchrl_wbrm.training.config import WBRMConfig, config_as_dict, to_config
from torchrl_wbrm.training.results import json_safe, write_json
from torchrl_wbrm.training.stops import TrainingDiverged
from torchrl_wbrm.training.trainer import WBRMTrainer, step_schedulers

__all__ = ["SeedGroup", "VECTORISED_ALGOS", "aggregate", "not_vectorised", "run_seeds", "seed_config",
           "summarise_seeds"]

#: the algorithms whose two stages are vectorised over seeds
VECTORISED_ALGOS = ("wbrm", "brm", "fqi")

_VALUE, _ACTOR = "value_network_params", "actor_network_params"
_TARGET_VALUE, _TARGET_ACTOR = "target_value_network_params", "target_actor_network_params"


def _logger_for(loggers: dict | None, seed: int):
    """Seed ``seed``'s logger: ``loggers[seed]`` (``None`` if absent), or without ``loggers`` the one its config
    names (the trainer's ``logger="config"``)."""
    return "config" if loggers is None else loggers.get(int(seed))


def seed_config(cfg: WBRMConfig, seed: int) -> WBRMConfig:
    """``cfg`` as the separate run with ``seed`` (``seeds`` unset): the config a seed's trainer runs and records."""
    node = OmegaConf.structured(cfg)
    node.seed, node.seeds = int(seed), None
    return OmegaConf.to_object(node)


def not_vectorised(cfg: WBRMConfig) -> str | None:
    """Why ``cfg``'s seeds cannot be trained as one vectorised update (``None``: they can). The data's action type
    is checked later, on the built trainers (:meth:`SeedGroup.refusal`)."""
    if cfg.algo not in VECTORISED_ALGOS:
        return f"algo={cfg.algo} is not vectorised over seeds (only {', '.join(VECTORISED_ALGOS)} are)"
    if cfg.q.maximiser != "actor":
        return f"q.maximiser={cfg.q.maximiser} is not vectorised over seeds (only the actor's max is)"
    if cfg.q.ensemble_size != 1:
        return "q.ensemble_size > 1 is not vectorised over seeds"
    if cfg.q.weight_actor_loss:  # its ŵ check branches on the batch's values, which torch.vmap cannot trace
        return "q.weight_actor_loss is not vectorised over seeds"
    if cfg.ratio.normalisation_coefficient > 0 and cfg.algo == "wbrm" and cfg.ratio.source == "learned":
        return "ratio.normalisation_coefficient > 0 is not vectorised over seeds"
    return None


@contextmanager
def _swapped(module, params: dict):
    """``module``'s attributes named in ``params`` replaced by its values (instance attributes, found before
    ``nn.Module.__getattr__``'s registered parameters) for the block."""
    missing = object()
    saved = {name: module.__dict__.get(name, missing) for name in params}
    module.__dict__.update(params)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is missing:
                module.__dict__.pop(name, None)
            else:
                module.__dict__[name] = value


class _Flat(dict):
    """One seed's parameters of one network as a flat ``{dotted name: tensor}`` dict, read by the losses' network
    calls as they read a TensorDict (``items(True, True)``): handed through the vmap as a plain pytree, without a
    TensorDict's per-call batching walk."""

    def items(self, *args):
        return super().items()

    def values(self, *args):
        return super().values()

    def detach(self) -> "_Flat":
        return _Flat({k: v.detach() for k, v in super().items()})


def _flat(td: TensorDictBase) -> dict:
    return {".".join(k) if isinstance(k, tuple) else k: v for k, v in td.items(True, True)}


def _stack(tds: list[TensorDictBase], trainable: TensorDictBase | None = None) -> TensorDict:
    """The seeds' parameter TensorDicts stacked on a leading dimension (a copy); the entries that require a gradient
    in ``trainable`` (the first seed's) become leaves that require one."""
    stacked = torch.stack([td.data if hasattr(td, "data") else td for td in tds]).clone()
    if trainable is not None:
        for key, value in trainable.items(True, True):
            if isinstance(value, torch.Tensor) and value.requires_grad:
                stacked.set(key, stacked.get(key).detach().requires_grad_(True))
    return stacked


def _leaves(td: TensorDictBase) -> list[torch.Tensor]:
    return [v for v in td.values(True, True) if v.requires_grad]


def _clip_per_seed(params: list[torch.Tensor], max_norm: float) -> None:
    """``torch.nn.utils.clip_grad_norm_`` applied to each seed's slice of the stacked ``params`` on its own (the
    same rule: each gradient times ``min(1, max_norm / (‖g‖ + 1e-6))``, ‖g‖ over all of a seed's gradients)."""
    grads = [p.grad for p in params if p.grad is not None]
    if not grads:
        return
    norms = torch.stack([g.reshape(g.shape[0], -1).norm(2, dim=1) for g in grads]).norm(2, dim=0)
    coef = (max_norm / (norms + 1e-6)).clamp(max=1.0)
    for g in grads:
        g.mul_(coef.reshape(-1, *([1] * (g.ndim - 1))))


def _finite_rows(figures: dict[str, torch.Tensor]) -> torch.Tensor:
    """Per seed, whether every figure is finite (figures are ``[N]`` tensors)."""
    values = torch.stack([v.detach().float() for v in figures.values()])
    return torch.isfinite(values).all(0)


class _StackedBatches:
    """Each seed's batch from its own buffer (its :class:`BufferBatches`), drawn with its own generator as
    ``RandomSampler`` draws (one ``torch.randint`` per seed), gathered with one ``index_select`` per entry from the
    seeds' storages laid end to end; returns a ``[num_seeds, batch_size]`` TensorDict of ``keys``."""

    def __init__(self, sides: list[BufferBatches], keys=None):
        self.batch_size = sides[0].batch_size
        self.keys = [k for k in sides[0]._keys if keys is None or k in keys]
        self.lengths = [side.length for side in sides]
        self.device = sides[0].device
        offsets = torch.tensor([0, *self.lengths[:-1]]).cumsum(0)
        self.offsets = offsets.to(self.device).reshape(-1, 1)
        index = {k: i for i, k in enumerate(sides[0]._keys)}
        self.sources = [torch.cat([side._sources[index[k]] for side in sides]) for k in self.keys]

    def sample(self, generators: list[torch.Generator]) -> TensorDict:
        rows = [torch.randint(0, n, (self.batch_size,), generator=g) for n, g in zip(self.lengths, generators)]
        index = (torch.stack(rows).to(self.device) + self.offsets).reshape(-1)
        n = len(self.lengths)
        out = {k: src.index_select(0, index).reshape(n, self.batch_size, *src.shape[1:])
               for k, src in zip(self.keys, self.sources)}
        return TensorDict(out, batch_size=[n, self.batch_size], device=self.device)


class SeedGroup:
    """The seeds of one config, each a :class:`~torchrl_wbrm.training.trainer.WBRMTrainer` in ``run_dir/seed<s>``,
    trained by one vectorised update (see the module's docstring).

    Args:
        cfg: the config (``seeds`` lists the seeds; ``seed`` is ignored).
        run_dir: the run directory; each seed's trainer writes into ``run_dir/seed<s>``.

    Keyword Args:
        progress: show a progress bar per stage.
        loggers: ``seed -> logger`` (a torchrl ``Logger`` or ``None``), given to the seeds' trainers; without it
            (``None``) each seed's trainer makes the logger ``cfg.logger`` names in its folder, as a separate run.
    """

    def __init__(self, cfg, run_dir, *, progress: bool = True, loggers: dict | None = None):

        self.cfg: WBRMConfig = to_config(cfg)
        self.seeds = [int(s) for s in self.cfg.seeds]
        self.run_dir = Path(run_dir)
        self.progress = progress
        self.timing: dict[str, float] = {}
        t0 = time.perf_counter()
        self.trainers, self.generators = [], []
        for seed in self.seeds:
            trainer = WBRMTrainer(seed_config(self.cfg, seed), self.run_dir / f"seed{seed}", progress=False,
                                  logger=_logger_for(loggers, seed))
            generator = torch.Generator()
            generator.set_state(torch.get_rng_state())  # what this seed's separate run draws next
            self.trainers.append(trainer)
            self.generators.append(generator)
        self.device = self.trainers[0].device
        self.timing["setup"] = time.perf_counter() - t0
        self.diverged: dict[int, dict] = {}  # seed index -> its diverged results

    def refusal(self) -> str | None:
        """Why these seeds train one at a time (``None``: they are vectorised)."""
        reason = not_vectorised(self.cfg)
        if reason is None and getattr(self.trainers[0].algo.loss, "discrete", False):
            reason = "a Discrete action (a Q head over the actions) is not vectorised over seeds"
        if reason is None and not getattr(self.trainers[0].algo.loss, "has_actor", False):
            reason = "a loss without an actor is not vectorised over seeds"
        return reason

    # ------------------------------------------------------------------ shared pieces
    def _active(self) -> list[int]:
        return [i for i in range(len(self.seeds)) if i not in self.diverged]

    def _diverge(self, i: int, err: TrainingDiverged) -> None:
        trainer = self.trainers[i]
        err.checkpoint_step = None
        self.diverged[i] = trainer._diverged_results(err)

    def _bar(self, name: str, total: int):
        from tqdm.auto import tqdm

        return tqdm(total=total, desc=f"{name} ({len(self.seeds)} seeds)", disable=None if self.progress else True,
                    mininterval=0.5)

    def _record(self, name: str, step: int, figures: dict[str, torch.Tensor], active: list[int]) -> None:
        """The training figures of ``step`` into each active seed's history and logger, as the trainer's loop."""
        values = {k: v.detach().cpu().tolist() for k, v in figures.items()}
        for i in active:
            running = {k: float(v[i]) for k, v in values.items()}
            trainer = self.trainers[i]
            trainer._log({f"{name}/{k}": v for k, v in running.items()}, step)
            trainer.history.append({"stage": f"{name}_train", "step": step, **running})

    def _check_finite(self, name: str, step: int, figures: dict[str, torch.Tensor]) -> None:
        ok = _finite_rows(figures)
        if bool(ok.all()):
            return
        for i in self._active():
            if not bool(ok[i]):
                key = next(k for k, v in figures.items() if not math.isfinite(float(v[i])))
                self._diverge(i, TrainingDiverged(name, step, key, float(figures[key][i])))

    # ------------------------------------------------------------------ stage 1
    def _run_ratio(self) -> None:
        rc = self.cfg.ratio
        losses = [t.ratio_fitter.loss_module for t in self.trainers]
        call = losses[0]._network_call()
        keys = list(losses[0].ratio_network.in_keys)
        params = _stack([loss.ratio_network_params for loss in losses], losses[0].ratio_network_params)
        leaves = _leaves(params)
        optimiser = torch.optim.Adam(leaves, lr=rc.lr, weight_decay=rc.weight_decay, **adam_options(leaves))
        behaviour = _StackedBatches([t.ratio_batches._sides["behaviour"] for t in self.trainers], keys)
        expert = _StackedBatches([t.ratio_batches._sides["expert"] for t in self.trainers], keys)
        loss0 = losses[0]
        batch_size = behaviour.batch_size

        def seed_loss(p, b, e):
            w_b = call(p, {k: b[k] for k in keys}, b.batch_size).reshape(batch_size)
            w_e = call(p, {k: e[k] for k in keys}, e.batch_size).reshape(batch_size)
            loss = basu_power_divergence(w_b, w_e, alpha=loss0.alpha, relative_beta=loss0.relative_beta,
                                         non_negative_correction=loss0.non_negative_correction)
            return loss, {"density_ratio_behaviour_mean": w_b.detach().mean(),
                          "density_ratio_expert_mean": w_e.detach().mean()}

        vmapped = torch.vmap(seed_loss)
        stopped: set[int] = set()
        log_every, total = self.cfg.logger.log_every, rc.steps
        bar = self._bar("ratio", total)
        t_update = t_eval = 0.0
        try:
            for step in range(1, total + 1):
                t0 = time.perf_counter()
                b = behaviour.sample(self.generators)  # behaviour, then expert: PairedSampler's order
                e = expert.sample(self.generators)
                loss, diagnostics = vmapped(params, b, e)
                optimiser.zero_grad(set_to_none=True)
                loss.sum().backward()
                if rc.grad_clip:
                    _clip_per_seed(leaves, rc.grad_clip)
                optimiser.step()
                figures = {"loss_density_ratio": loss.detach(), **diagnostics}
                self._check_finite("ratio", step, figures)
                active = [i for i in self._active() if i not in stopped]
                if step % log_every == 0 or step == total:
                    self._record("ratio", step, figures, active)
                t1 = time.perf_counter()
                t_update += t1 - t0
                if step % rc.eval_every == 0 or step == total:
                    for i in active:
                        trainer = self.trainers[i]
                        with torch.no_grad():
                            for key, value in params.items(True, True):
                                trainer.ratio_fitter.loss_module.ratio_network_params.get(key).data.copy_(value[i])
                        trainer.state["step"] = step
                        trainer.ratio_fitter.num_steps = step
                        try:
                            if trainer._ratio_eval(step):
                                stopped.add(i)
                        except TrainingDiverged as err:
                            self._diverge(i, err)
                    t_eval += time.perf_counter() - t1
                bar.update(1)
                if all(i in stopped for i in self._active()):
                    break
        finally:
            bar.close()
        self.timing["ratio_updates"] = t_update
        self.timing["ratio_evaluations"] = t_eval

    # ------------------------------------------------------------------ stage 2
    def q_update(self) -> "_QUpdate":
        """Stage 2's vectorised update over the seeds' built losses and buffers (after :meth:`WBRMTrainer._build_q_buffer`)."""
        return _QUpdate(self)

    def _run_q(self) -> None:
        qc = self.cfg.q
        update = self.q_update()
        log_every, total, eval_every = self.cfg.logger.log_every, qc.steps, qc.eval_every
        bar = self._bar("q", total)
        t_update = t_eval = 0.0
        try:
            for step in range(1, total + 1):
                t0 = time.perf_counter()
                figures = update.step(step, *update.sample(step))
                if self.device.type == "cpu" or step % log_every == 0 or step % eval_every == 0 or step == total:
                    self._check_finite("q", step, figures)
                active = self._active()
                if step % log_every == 0 or step == total:
                    self._record("q", step, figures, active)
                t1 = time.perf_counter()
                t_update += t1 - t0
                if step % eval_every == 0 or step == total:
                    self._evaluate(update.params, step, active)
                    t_eval += time.perf_counter() - t1
                bar.update(1)
                if not active:
                    break
        finally:
            bar.close()
            update.close()
        self.timing["q_updates"] = t_update
        self.timing["q_evaluations"] = t_eval

    @torch.no_grad()
    def _load_seed(self, params: dict, i: int) -> None:
        """Seed ``i``'s slice of the stacked parameters into its trainer's loss."""
        loss = self.trainers[i].algo.loss
        for name, stacked in params.items():
            own = getattr(loss, name)
            for key, value in stacked.items(True, True):
                own.get(key).data.copy_(value[i])

    def _evaluate(self, params: dict, step: int, active: list[int]) -> None:
        for i in active:
            trainer = self.trainers[i]
            self._load_seed(params, i)
            trainer.state["step"] = step
            try:
                trainer._q_eval(step)
            except TrainingDiverged as err:
                self._diverge(i, err)

    # ------------------------------------------------------------------ run
    def run(self) -> list[dict]:
        """Both stages for every seed; returns each seed's results (as its ``results.json``), in ``seeds`` order."""
        try:
            if self.trainers[0].ratio_network is not None:
                self._run_ratio()
            t0 = time.perf_counter()
            for i, trainer in enumerate(self.trainers):
                if i in self.diverged:
                    continue
                if trainer.ratio_fitter is not None:
                    trainer.ratio_fitter.best_network()  # the best held-out state
                trainer.state = {"stage": "q", "step": 0}
                try:
                    trainer._build_q_buffer()
                except TrainingDiverged as err:
                    self._diverge(i, err)
            self.timing["weights_over_d"] = time.perf_counter() - t0
            if self._active():
                self._run_q()
            t0 = time.perf_counter()
            results = []
            for i, trainer in enumerate(self.trainers):
                if i in self.diverged:
                    results.append(self.diverged[i])
                    continue
                trainer.state = {"stage": "done", "step": self.cfg.q.steps}
                results.append(trainer.results())
            self.timing["results"] = time.perf_counter() - t0
            return results
        finally:
            for trainer in self.trainers:
                trainer.release()


class _QUpdate:
    """Stage 2's step for every seed at once (see the module's docstring): ``sample(step)`` draws each seed's batch
    (and, with ``q.expert_bc_alpha``, its S^e batch on actor steps) with its own generator, ``step(step, batch,
    expert)`` makes the Q step, every ``q.actor_delay`` steps the actor step and the target update, then steps the
    schedules; it returns the figures as ``[num_seeds]`` tensors."""

    def __init__(self, group: SeedGroup):
        self.cfg = cfg = group.cfg
        qc = cfg.q
        self.generators = group.generators
        losses = [t.algo.loss for t in group.trainers]
        self.loss = loss0 = losses[0]
        for name in ("value_network", "actor_network"):
            loss0._network_call(name)  # built (and cached) on the loss's own parameters, before any swap
        loss0._network_facts()
        names = [_VALUE, _ACTOR] + ([_TARGET_VALUE] if loss0.delay_value else []) + (
            [_TARGET_ACTOR] if loss0.delay_actor else [])
        self.params = {n: _stack([getattr(loss, n) for loss in losses],
                                 getattr(loss0, n) if n in (_VALUE, _ACTOR) else None) for n in names}
        self.stacked = {name: _flat(td) for name, td in self.params.items()}  # the same tensors, as a plain pytree
        self.value_leaves, actor_leaves = _leaves(self.params[_VALUE]), _leaves(self.params[_ACTOR])
        self.optimisers = {"value": torch.optim.Adam(self.value_leaves, lr=qc.lr, **adam_options(self.value_leaves)),
                           "actor": torch.optim.Adam(actor_leaves, lr=qc.actor_lr, **adam_options(actor_leaves))}
        self.schedulers = {}
        if qc.lr_schedule == "cosine":
            self.schedulers = {k: torch.optim.lr_scheduler.CosineAnnealingLR(o, T_max=qc.steps)
                               for k, o in self.optimisers.items()}
        self.batches = _StackedBatches([t._q_batches() for t in group.trainers], set(loss0.in_keys) | {"density_ratio"})
        clonings = [t.algo.__dict__.get("cloning") or _expert_cloning(t) for t in group.trainers]
        self.cloning = clonings[0]
        self.expert = None
        self._saved_buffer = None
        if self.cloning is not None:
            self._saved_buffer = self.cloning.buffer
            self.cloning.network_call(loss0.actor_network_params)  # built on the loss's own parameters
            keys = set(self.cloning.actor.in_keys) | {"action"}
            self.expert = _StackedBatches([BufferBatches(c.buffer, qc.batch_size) for c in clonings], keys)
        self.reward_key = ("next", loss0.tensor_keys.reward)
        self.fqi = cfg.algo == "fqi"
        self.hard_every = cfg.baselines.fqi.target_update_every if self.fqi else None
        self.hard_counter = 0
        self.soft_weight = 1 - (1 - qc.target_tau)  # torchrl's SoftUpdate: lerp by 1 − eps, eps = 1 − τ
        self.vmapped_value = torch.vmap(self._value_loss)
        self.vmapped_actor = torch.vmap(self._actor_loss)

    def _swap(self, p):
        p = {name: _Flat(value) for name, value in p.items()}
        return _swapped(self.loss, {_VALUE: p[_VALUE], _ACTOR: p[_ACTOR],
                                    _TARGET_VALUE: p[_TARGET_VALUE] if _TARGET_VALUE in p else p[_VALUE].detach(),
                                    _TARGET_ACTOR: p[_TARGET_ACTOR] if _TARGET_ACTOR in p else p[_ACTOR].detach()})

    def _value_loss(self, p, batch):
        """One seed's Q loss and figures (inside the vmap): the loss's own pieces with this seed's parameters."""
        loss0 = self.loss
        with self._swap(p):
            q_value = loss0._chosen_q(batch)
            next_value = loss0.next_state_value(batch)
            target = per_sample(loss0._target(batch, next_value), batch.batch_size, self.reward_key)
            weight = loss0._weight(batch, check=False)
            loss = weighted_bellman_residual(q_value, target, weight, residual=loss0.residual,
                                             reduction=loss0.reduction)
        with torch.no_grad():
            delta = bellman_residual(q_value, target)
            figures = {"td_error_mean": delta.mean(), "td_error_abs_mean": delta.abs().mean(),
                       "q_mean": q_value.mean(), "target_value_mean": target.mean()}
            if loss0.use_weights:
                figures.update(weight_mean=weight.mean(), weight_ess=effective_sample_size(weight))
        return loss, figures

    def _actor_loss(self, p, batch, expert_batch=None):
        """One seed's actor loss (inside the vmap): ``WeightedBellmanLoss.actor_loss``, then the S^e cloning term
        (and, with ``q.expert_bc_weighted_d``, the ŵ-weighted cloning of this seed's D batch)."""
        with self._swap(p):
            loss, diagnostics = self.loss.actor_loss(batch)
            figures = {k: v for k, v in diagnostics.items() if k == "bc_loss"}
            if expert_batch is not None:
                self.cloning.buffer = _Given(expert_batch)
                loss, bc = self.cloning(loss, diagnostics["actor_q_abs_mean"], _Flat(p[_ACTOR]), batch)
                figures.update(bc)
        return loss, figures

    def sample(self, step: int):
        """Each seed's Q batch, then (on actor steps with a cloning term) its S^e batch: a separate run's order."""
        batch = self.batches.sample(self.generators)
        actor_step = step % self.cfg.q.actor_delay == 0
        expert = self.expert.sample(self.generators) if actor_step and self.expert is not None else None
        return batch, expert

    def step(self, step: int, batch, expert=None) -> dict[str, torch.Tensor]:
        qc = self.cfg.q
        loss_value, figures = self.vmapped_value(self.stacked, batch)
        self.optimisers["value"].zero_grad(set_to_none=True)
        loss_value.sum().backward()
        if qc.grad_clip:
            _clip_per_seed(self.value_leaves, qc.grad_clip)
        self.optimisers["value"].step()
        figures = {"loss_value": loss_value.detach(), **figures}
        if self.fqi:  # torchrl's HardUpdate: a copy on the calls where its counter reaches the interval
            if self.hard_counter == self.hard_every:
                self._copy_targets()
                self.hard_counter = 0
            else:
                self.hard_counter += 1
        if step % qc.actor_delay == 0:
            args = (self.stacked, batch) if expert is None else (self.stacked, batch, expert)
            loss_actor, actor_figures = self.vmapped_actor(*args)
            self.optimisers["actor"].zero_grad(set_to_none=True)
            loss_actor.sum().backward()
            self.optimisers["actor"].step()
            figures.update(loss_actor=loss_actor.detach(), **actor_figures)
            if not self.fqi and self.loss.delay_value:
                self._soft_update()
        step_schedulers(self.schedulers)
        return figures

    def close(self) -> None:
        if self.cloning is not None:
            self.cloning.buffer = self._saved_buffer

    def _pairs(self):
        for source, target in ((_VALUE, _TARGET_VALUE), (_ACTOR, _TARGET_ACTOR)):
            if target in self.params:
                for s, d in zip(self.params[source].values(True, True), self.params[target].values(True, True)):
                    if s.is_floating_point():
                        yield s, d

    @torch.no_grad()
    def _soft_update(self) -> None:
        pairs = list(self._pairs())
        torch._foreach_lerp_([d for _, d in pairs], [s.detach() for s, _ in pairs], self.soft_weight)

    @torch.no_grad()
    def _copy_targets(self) -> None:
        for s, d in self._pairs():
            d.copy_(s)


class _Given:
    """A stand-in replay buffer whose ``sample()`` returns the batch it holds (a seed's expert batch, drawn with
    that seed's generator, handed to :class:`~torchrl_wbrm.algos.base.ExpertCloning` inside the vmap)."""

    def __init__(self, batch):
        self.batch = batch

    def sample(self):
        return self.batch


def _expert_cloning(trainer):
    """The actor's S^e cloning term of ``trainer``'s algo (``q.expert_bc_alpha``), as its step builds it, or None."""
    qc = trainer.cfg.q
    if not qc.expert_bc_alpha or trainer.cfg.algo not in ("wbrm", "brm"):
        return None
    from torchrl_wbrm.algos.base import ExpertCloning

    return ExpertCloning(trainer.actor, trainer.datasets.expert_samples[:], trainer.action_spec,
                         alpha=qc.expert_bc_alpha, batch_size=qc.batch_size, weighted_d=qc.expert_bc_weighted_d)


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


def _combined(cfg: WBRMConfig, runs: list[dict], *, vectorised: bool, reason: str | None, timing: dict) -> dict:
    statuses = [r.get("status", "finished") for r in runs]
    return json_safe({
        "status": "finished" if all(s == "finished" for s in statuses) else "diverged",
        "kind": "seeds",
        "env": cfg.env.name,
        "algo": cfg.algo,
        "seeds": [int(s) for s in cfg.seeds],
        "seeds_diverged": [int(r["seed"]) for r in runs if r.get("status", "finished") != "finished"],
        "vectorised": vectorised,
        "not_vectorised_because": reason,
        "aggregate": {"final": aggregate(runs), "level": 0.95},
        "runs": runs,
        "timing": timing,
        "config": config_as_dict(cfg),
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
        done = seed_dir / "results.json"
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


def run_seeds(cfg, run_dir, *, progress: bool = True, loggers: dict | None = None, vectorise: bool = True,
              resume: bool = False) -> dict:
    """Train ``cfg.seeds`` in one process into ``run_dir`` (``run_dir/seed<s>`` per seed) and write
    ``run_dir/results.json`` (every seed's results under ``"runs"``, the aggregate under ``"aggregate"``).

    ``vectorise=False`` trains the seeds one at a time (what a config :func:`not_vectorised` refuses gets); a refusal
    is printed in one line on stderr. ``cfg.overwrite``: an earlier run in ``run_dir`` is replaced whole (its
    ``results.json`` and every ``seed<s>/`` folder's outputs, the seeds this run does not train included).
    ``resume``: continue an interrupted multi-seed run in ``run_dir``: its finished seeds are kept (their results
    reused, for this config only), a seed whose folder holds a checkpoint resumes from it, and the others run anew.
    Returns the combined results.
    """
    import sys

    from torchrl_wbrm.training.rundir import clear_run_outputs, holds_run

    cfg = to_config(cfg)
    if not cfg.seeds:
        raise ValueError("run_seeds needs cfg.seeds, a list of seeds.")
    run_dir = Path(run_dir)
    start = time.perf_counter()
    finished, checkpointed = _earlier_seeds(cfg, run_dir) if resume else ({}, [])
    if not resume and cfg.overwrite and holds_run(run_dir):
        clear_run_outputs(run_dir)  # the earlier multi-seed run goes whole: no stale seed<s>/ outlives it
    todo = [int(s) for s in cfg.seeds if int(s) not in finished and int(s) not in checkpointed]
    if resume:
        for seed in todo:  # an unfinished seed without a checkpoint runs anew: its partial logs go first
            clear_run_outputs(run_dir / f"seed{seed}")
    runs_by_seed: dict[int, dict] = dict(finished)
    timing = {"setup": 0.0, "training": 0.0}
    for seed in checkpointed:  # interrupted seeds of a run trained one at a time: each resumes on its own
        t0 = time.perf_counter()
        trainer = WBRMTrainer(seed_config(cfg, seed), run_dir / f"seed{seed}", progress=progress,
                              logger=_logger_for(loggers, seed), resume=True)
        t1 = time.perf_counter()
        runs_by_seed[seed] = trainer.run()
        timing["setup"] += t1 - t0
        timing["training"] += time.perf_counter() - t1
    reason = "no seed left to train" if not todo else not_vectorised(cfg) if vectorise else "vectorise=False"
    group = None
    rest = seed_config(cfg, todo[0]) if todo else None
    if todo:
        node = OmegaConf.structured(rest)
        node.seeds = todo
        rest = OmegaConf.to_object(node)
    if todo and reason is None:
        group = SeedGroup(rest, run_dir, progress=progress, loggers=loggers)
        reason = group.refusal()
    if todo and reason is None:
        runs_by_seed.update(zip(todo, group.run()))
        timing.update({k: timing.get(k, 0.0) + v for k, v in group.timing.items()})
    elif todo:
        if vectorise:
            print(f"seeds: {reason}; training the {len(todo)} seeds one at a time in this process.",
                  file=sys.stderr)
        for i, seed in enumerate(todo):
            t0 = time.perf_counter()
            if group is not None:  # built, then refused on the data: its trainers run, each from its own draws
                trainer = group.trainers[i]
                torch.set_rng_state(group.generators[i].get_state())
            else:
                trainer = WBRMTrainer(seed_config(cfg, seed), run_dir / f"seed{seed}", progress=progress,
                                      logger=_logger_for(loggers, seed))
            t1 = time.perf_counter()
            runs_by_seed[seed] = trainer.run()
            timing["setup"] += t1 - t0
            timing["training"] += time.perf_counter() - t1
    runs = [runs_by_seed[int(s)] for s in cfg.seeds]
    timing["total"] = time.perf_counter() - start
    results = _combined(cfg, runs, vectorised=reason is None, reason=reason, timing=timing)
    results["wall_seconds"] = timing["total"]
    write_json(run_dir / "results.json", results)
    return results


def summarise_seeds(results: dict) -> str:
    """A few lines: each seed's headline figure and status, and the mean ± 95% CI over the seeds."""
    figure = next((k for k in ("regret", "return") if k in results["aggregate"]["final"]), None)
    lines = [f"env {results['env']}  algo {results['algo']}  seeds {results['seeds']}  "
             f"({'vectorised over seeds' if results['vectorised'] else 'one seed at a time'})"]
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
