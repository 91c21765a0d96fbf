"""What every algorithm is built from: :class:`AlgoContext` (what a builder gets from the trainer), :class:`Algo` (what
it returns) and the pieces the builders share (Adam, the critic and actor options, the Bellman-residual step)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded
from torchrl.modules import ValueOperator
from torchrl.objectives import LossModule

from torchrl_wbrm.keys import DENSITY_RATIO
from torchrl_wbrm.modules import make_deterministic_actor, make_discrete_q_network, make_q_network
from torchrl_wbrm.objectives import WeightedBellmanLoss
from torchrl_wbrm.objectives._fast import NetworkCall
from torchrl_wbrm.objectives._fast import ForeachSoftUpdate  # torchrl's SoftUpdate, one foreach lerp per step
from torchrl_wbrm.objectives._utils import get_entry
from torchrl_wbrm.objectives.functional import action_cloning, td3bc_lambda

#: the recipe's schema, :class:`torchrl_wbrm.training.config.WBRMConfig` (a layer above this one: only its fields are
#: read here, never imported)
WBRMConfig = Any

__all__ = [
    "Algo",
    "AlgoContext",
    "actor_options",
    "adam",
    "adam_options",
    "bellman_residual_algo",
    "discrete_bellman_residual_algo",
    "bellman_step",
    "check_positive",
    "critic_actor_optimisers",
    "critic_options",
    "descend",
    "descend_all",
    "deterministic_actor",
    "ExpertCloning",
    "q_network",
    "q_reader",
    "scalars",
]

StepFn = Callable[[TensorDictBase, int], dict]
QValueFn = Callable[[TensorDictBase], "tuple[torch.Tensor, torch.Tensor]"]


@dataclass
class AlgoContext:
    """What a builder needs from the trainer: the config, the problem's sizes, the Q output bias, (with
    ``q.normalise_observations``) the data's observation mean and standard deviation for the networks' input, and
    the environment's :class:`~torchrl_wbrm.tasks.Task` (what a builder may ask of the env, e.g. DQN's action
    grid, without knowing which env it is)."""

    cfg: WBRMConfig
    observation_dim: int
    action_dim: int
    action_spec: Bounded
    gamma: float
    q_initial_bias: float
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    observation_loc: torch.Tensor | None = None
    observation_scale: torch.Tensor | None = None
    task: Any = None


@dataclass
class Algo:
    """One method, ready for the trainer's loop.

    Attributes:
        loss: the LossModule (its ``state_dict`` holds every network and target; checkpointed).
        optimisers: name -> optimiser (checkpointed).
        step: ``step(batch, step) -> dict`` of scalar figures: one update on one batch.
        policy: the module evaluated (deterministic mode) in the env; reads ``"observation"``, writes ``"action"``.
        q_value: ``q_value(td) -> (Q̂, action)``: Q̂(x, a) at ``td``'s state-actions (shape ``[N]``) and the actions
            at which it was evaluated (the nearest grid point for DQN), for the Q* error; ``None`` to skip it.
        data: ``"transitions"`` (D) or ``"expert"`` (S^e).
        map_data: applied once to the training data before it enters the buffer (DQN: actions -> grid indices).
        bellman_loss: a :class:`~torchrl_wbrm.objectives.WeightedBellmanLoss` whose unweighted residual on held-out
            episodes of D is reported (``None``: not reported).
        uses_ratio: the method reads the stage-1 weights ŵ (only ``wbrm``).
        cloning: the actor's S^e cloning term (:class:`ExpertCloning`, ``q.expert_bc_alpha``), which the trainer
            extends with D's expert-like episodes after stage 1 (``q.expert_bc_from_d``); ``None``: none.
        marks_expert_like: the trainer marks the rows of D's expert-like episodes
            (:func:`~torchrl_wbrm.ratio.expert_like_episodes` of the raw ŵ) under the key ``"expert_like"`` before
            ``map_data`` (``bc`` with ``baselines.bc.data=expert_like``).
    """

    loss: LossModule
    optimisers: dict[str, torch.optim.Optimizer]
    step: StepFn
    policy: TensorDictModuleBase
    q_value: QValueFn | None = None
    data: str = "transitions"
    map_data: Callable[[TensorDictBase], TensorDictBase] | None = None
    bellman_loss: WeightedBellmanLoss | None = None
    uses_ratio: bool = False
    cloning: "ExpertCloning | None" = None
    marks_expert_like: bool = False


# ---------------------------------------------------------------------- shared pieces
def descend(loss: torch.Tensor, optimiser: torch.optim.Optimizer, grad_clip: float | None = None) -> None:
    """One gradient step of ``optimiser`` on ``loss`` (optionally clipping the gradient norm of its parameters)."""
    optimiser.zero_grad(set_to_none=True)
    loss.backward()
    if grad_clip:
        params = [p for group in optimiser.param_groups for p in group["params"]]
        torch.nn.utils.clip_grad_norm_(params, grad_clip)
    optimiser.step()


def descend_all(losses: dict[str, torch.Tensor], optimisers: dict[str, torch.optim.Optimizer]) -> None:
    """Sum ``losses``, backpropagate once and step every optimiser.

    For torchrl losses whose terms each reach only their own network (TorchRL detaches the critic in the actor loss,
    and the targets), this is the usual simultaneous update of torchrl's sota-implementations (CQL, IQL).
    """
    for optimiser in optimisers.values():
        optimiser.zero_grad(set_to_none=True)
    sum(losses.values()).backward()
    for optimiser in optimisers.values():
        optimiser.step()


def adam_options(params) -> dict:
    """``fused=True`` where torch has a fused Adam for every parameter (floating point, on CPU or CUDA): one kernel
    per parameter instead of a dozen. It changes the
    update only in floating-point order (≤ 1 ulp per step against the default for-loop Adam)."""
    params = list(params)
    ok = bool(params) and all(p.is_floating_point() and p.device.type in ("cpu", "cuda") for p in params)
    return {"fused": True} if ok else {}


def adam(params, lr: float) -> torch.optim.Adam:
    params = list(params)
    return torch.optim.Adam(params, lr=lr, **adam_options(params))


def critic_actor_optimisers(loss: LossModule, cfg: WBRMConfig, critic: str = "value") -> dict[str, torch.optim.Optimizer]:
    """Adam for the loss's ``<critic>_network_params`` (``q.lr``) and ``actor_network_params`` (``q.actor_lr``), named
    ``critic`` and ``"actor"`` (the names are checkpoint keys)."""
    return {
        critic: adam(getattr(loss, f"{critic}_network_params").values(True, True), cfg.q.lr),
        "actor": adam(loss.actor_network_params.values(True, True), cfg.q.actor_lr),
    }


def scalars(figures: dict | TensorDictBase) -> dict:
    return {k: v.detach() for k, v in figures.items() if isinstance(v, torch.Tensor) and v.ndim == 0}


def q_reader(network: TensorDictModuleBase, params, value_key="state_action_value") -> QValueFn:
    """Q̂(x, a) of a continuous-action Q network loaded with ``params`` (the first member of an ensemble)."""

    def q_value(td: TensorDictBase):
        with params.to_module(network):
            q = network(td.select(*network.in_keys).clone())[value_key]
        return q.reshape(-1), td["action"]

    return q_value


def critic_options(ctx: AlgoContext) -> dict:
    """The network options of every critic (Q, V, DQN's head): ``q.num_cells``, ``q.activation``, ``q.layer_norm``,
    the ensemble, ``q.value_scale``, the output bias and the input normalisation."""
    qc = ctx.cfg.q
    return dict(num_cells=qc.num_cells, activation=qc.activation, layer_norm=qc.layer_norm,
                initial_bias=ctx.q_initial_bias, num_members=qc.ensemble_size,
                ensemble_reduction=qc.ensemble_reduction, value_scale=qc.value_scale,
                observation_loc=ctx.observation_loc, observation_scale=ctx.observation_scale)


def actor_options(ctx: AlgoContext) -> dict:
    """The network options of every actor: ``q.actor_num_cells``, ``q.actor_activation``, ``q.actor_layer_norm`` and
    the input normalisation."""
    qc = ctx.cfg.q
    return dict(num_cells=qc.actor_num_cells, activation=qc.actor_activation, layer_norm=qc.actor_layer_norm,
                observation_loc=ctx.observation_loc, observation_scale=ctx.observation_scale)


def q_network(ctx: AlgoContext) -> ValueOperator:
    return make_q_network(ctx.observation_dim, ctx.action_dim, **critic_options(ctx)).to(ctx.device)


def deterministic_actor(ctx: AlgoContext):
    return make_deterministic_actor(ctx.observation_dim, ctx.action_spec, **actor_options(ctx)).to(ctx.device)


class ExpertCloning:
    """The actor's support term: TD3+BC's cloning, toward the expert's actions in S^e, in unit actions.

    The actor step minimises ``λ · (−mean_D Q(x, μ(x))) + mean_{S^e} ‖(μ(x_e) − a_e) / h‖² / m``, with
    ``λ = α / mean_D |Q(x, μ(x))|`` (:func:`~torchrl_wbrm.objectives.functional.td3bc_lambda`: Fujimoto & Gu's
    normalisation, the Q term has the same size whatever the reward scale; the mean of ``|Q|``, not ``|mean Q|``,
    which passes through 0 when Q changes sign during training and then makes λ
    explode and the Q term pull the actor off the expert) and ``h`` the half-width of the action box (the cloning
    term has the same size whatever the action bounds; ``m`` the action dimension).
    S^e, the expert samples the method already holds for stage 1, keeps μ on the expert's support; Q then moves it
    only where Q says it pays. Its batches are drawn from a torchrl replay buffer over S^e with the global generator
    (checkpointed with the run), as the buffer's ``sample()`` draws them, gathered by
    :class:`~torchrl_wbrm.data.sampling.BufferBatches` (the same indices, without the buffer's per-call bookkeeping).

    With ``weighted_d`` (``q.expert_bc_weighted_d``) the actor also clones the actions of the D batch its step
    receives, each row weighted by its stored ŵ (``weight_key``, the trainer's ``"density_ratio"``, after its
    shaping) and self-normalised over the batch: the loss gains ``Σ_b w_b ‖(μ(x_b) − a_b) / h‖² / m / Σ_b w_b``
    (:func:`~torchrl_wbrm.objectives.functional.action_cloning`, as the S^e term), so μ clones S^e and the rows of
    D that ŵ calls expert-like. Where there is no ŵ (``algo=brm``, ``ratio.source=none``) the stored weight is 1
    and the term is the plain cloning of D's actions.

    Args:
        actor: the actor (its parameters are the loss's ``actor_network_params``).
        expert_samples: S^e, a TensorDict with the actor's in_keys and ``"action"``.
        action_spec: the action box.
        alpha: α.
        batch_size: S^e samples per actor step.
        weighted_d: add the weighted cloning of the D batch (the ``batch`` each call is given).
        weight_key: the D batch's entry holding each row's weight.
    """

    def __init__(self, actor, expert_samples: TensorDictBase, action_spec: Bounded, *, alpha: float,
                 batch_size: int, weighted_d: bool = False, weight_key: str = DENSITY_RATIO) -> None:
        from torchrl_wbrm.data import make_replay_buffer

        if not alpha > 0:
            raise ValueError(f"q.expert_bc_alpha must be > 0 or null, got {alpha!r}.")
        self.actor, self.alpha = actor, float(alpha)
        self.weighted_d, self.weight_key = bool(weighted_d), weight_key
        self.keys, self.batch_size = list(actor.in_keys) + ["action"], batch_size
        self.expert_samples = expert_samples.select(*self.keys)
        self.buffer = make_replay_buffer(self.expert_samples, batch_size=batch_size)
        self.added_rows = 0
        self.centre = ((action_spec.space.high + action_spec.space.low) / 2).to(torch.float32)
        self.half_width = ((action_spec.space.high - action_spec.space.low) / 2).clamp_min(1e-6).to(torch.float32)

    def __call__(self, loss_q: torch.Tensor, q_abs_mean: torch.Tensor, params,
                 batch: TensorDictBase | None = None) -> tuple[torch.Tensor, dict]:
        """``loss_q = −mean_D Q(x, μ(x))`` and ``q_abs_mean = mean_D |Q(x, μ(x))|`` (``actor_loss``'s
        ``"actor_q_abs_mean"``); returns the actor's loss and the cloning terms (detached). ``batch``: the actor
        step's D batch, needed with :attr:`weighted_d`."""
        batches = self.batches()
        expert = self.buffer.sample() if batches is None else batches.sample()
        call = self.network_call(params)
        mu = call(params, {key: expert.get(key) for key in self.actor.in_keys}, expert.batch_size)
        if self.half_width.device != mu.device:
            self.half_width = self.half_width.to(mu.device)
        bc = action_cloning(mu, expert["action"], self.half_width)
        loss = td3bc_lambda(self.alpha, q_abs_mean) * loss_q + bc
        figures = {"expert_bc_loss": bc.detach()}
        if self.weighted_d:
            if batch is None:
                raise ValueError("ExpertCloning(weighted_d=True) clones the actor step's D batch: pass it as batch=.")
            mu_d = call(params, {key: batch.get(key) for key in self.actor.in_keys}, batch.batch_size)
            bc_d = action_cloning(mu_d, batch["action"], self.half_width,
                                  get_entry(batch, self.weight_key, "each D row's cloning weight"))
            loss = loss + bc_d
            figures["weighted_d_bc_loss"] = bc_d.detach()
        return loss, figures

    def add_expert_like(self, rows: TensorDictBase) -> None:
        """Clone ``rows`` (D's expert-like episodes, ``q.expert_bc_from_d``) as S^e is: the term's buffer becomes
        one over S^e's samples and ``rows``. Replaces any earlier call's rows."""
        from torchrl_wbrm.data import make_replay_buffer

        rows = rows.select(*self.keys).to(self.expert_samples.device)
        self.buffer = make_replay_buffer(torch.cat([self.expert_samples, rows], 0), batch_size=self.batch_size)
        self.added_rows = rows.shape[0]

    def batches(self):
        """S^e's batches: :class:`~torchrl_wbrm.data.sampling.BufferBatches` over :attr:`buffer` (the indices
        ``buffer.sample()`` would draw, gathered into tensors allocated once), built on first use and again when
        :attr:`buffer` is replaced; ``None`` where :attr:`buffer` is not a replay buffer ``BufferBatches`` reads (a
        buffer with another sampler, or any object with a ``sample()``): its ``sample()`` is then called."""
        from torchrl.data import TensorDictReplayBuffer

        from torchrl_wbrm.data.sampling import BufferBatches

        cached = self.__dict__.get("_batches")
        if cached is None or cached[0] is not self.buffer:
            batches = None
            if isinstance(self.buffer, TensorDictReplayBuffer):
                try:
                    batches = BufferBatches(self.buffer)
                except (TypeError, ValueError):
                    batches = None
            cached = self._batches = (self.buffer, batches)
        return cached[1]

    def network_call(self, params) -> NetworkCall:
        """How μ is called: a :class:`~torchrl_wbrm.objectives._fast.NetworkCall` of the actor, built on the first
        ``params`` seen (the loss's ``actor_network_params``: their tensors go straight into the actor's slots) and
        kept; the same μ, gradient included, as ``with params.to_module(actor): actor(td)``."""
        call = self.__dict__.get("_network_call")
        if call is None:
            call = self._network_call = NetworkCall(self.actor, params, "action", why="the actor's action")
        return call


def bellman_step(loss: WeightedBellmanLoss, optimisers, cfg: WBRMConfig, *, updater=None, every_step=False,
                 cloning: ExpertCloning | None = None) -> StepFn:
    """The step of the Bellman-residual family (wbrm, fqi): a Q step, and every ``q.actor_delay`` steps an actor step.

    ``updater`` is stepped after each actor step (``SoftUpdate``) or, with ``every_step``, after every Q step
    (``HardUpdate`` counts calls and copies every K of them).
    """
    qc = cfg.q

    def step(batch: TensorDictBase, i: int) -> dict:
        loss_value, figures = loss.value_loss(batch)
        descend(loss_value, optimisers["value"], qc.grad_clip)
        out = {"loss_value": loss_value.detach(), **scalars(figures)}
        if updater is not None and every_step:
            updater.step()
        if i % qc.actor_delay == 0 and loss.has_actor:
            loss_actor, actor_figures = loss.actor_loss(batch)
            if cloning is not None:
                loss_actor, bc_figures = cloning(loss_actor, actor_figures["actor_q_abs_mean"],
                                                 loss.actor_network_params, batch)
                out.update(bc_figures)
            descend(loss_actor, optimisers["actor"])
            out["loss_actor"] = loss_actor.detach()
            if updater is not None and not every_step:
                updater.step()
        return out

    return step


def bellman_residual_algo(ctx: AlgoContext, *, weighted: bool) -> Algo:
    """The Bellman-residual family of the paper (``wbrm``, ``brm``): Q by the (weighted) residual, an actor as the
    maximiser, targets by ``SoftUpdate`` or residual gradient (``q.bootstrap``). A ``Discrete`` action (Minari
    datasets, read one-hot): :func:`discrete_bellman_residual_algo`."""
    datasets = getattr(ctx.task, "datasets", None)
    num_actions = datasets.metadata.get("discrete_actions") if datasets is not None else None
    if num_actions:
        return discrete_bellman_residual_algo(ctx, weighted=weighted, num_actions=int(num_actions))
    qc = ctx.cfg.q
    value_network, actor = q_network(ctx), deterministic_actor(ctx)
    loss = WeightedBellmanLoss(
        value_network,
        actor_network=actor,
        residual=qc.residual,
        delay_value=qc.bootstrap == "target",
        residual_gradient=qc.bootstrap == "residual_gradient",
        use_weights=weighted,
        maximiser=qc.maximiser,
        action_spec=ctx.action_spec,
        num_action_samples=qc.num_action_samples,
        weight_actor_loss=qc.weight_actor_loss,
        bc_alpha=qc.bc_alpha or None,  # 0: off
    )
    loss.make_value_estimator(gamma=ctx.gamma)
    updater = ForeachSoftUpdate(loss, tau=qc.target_tau) if qc.bootstrap == "target" else None
    optimisers = critic_actor_optimisers(loss, ctx.cfg)
    cloning = None
    if qc.expert_bc_alpha:  # the actor's support term, toward S^e's actions (validate_config: not with bc_alpha)
        cloning = ExpertCloning(actor, ctx.task.datasets.expert_samples[:], ctx.action_spec,
                                alpha=qc.expert_bc_alpha, batch_size=qc.batch_size,
                                weighted_d=qc.expert_bc_weighted_d)
    return Algo(
        loss=loss,
        optimisers=optimisers,
        step=bellman_step(loss, optimisers, ctx.cfg, updater=updater, cloning=cloning),
        policy=actor,
        q_value=q_reader(loss.value_network, loss.value_network_params),
        bellman_loss=loss,
        uses_ratio=weighted,
        cloning=cloning,
    )


def discrete_bellman_residual_algo(ctx: AlgoContext, *, weighted: bool, num_actions: int) -> Algo:
    """``wbrm`` / ``brm`` for a ``Discrete(n)`` action (stored one-hot): a Q head over the ``n`` actions
    (``make_discrete_q_network``), the max over next actions exact (``WeightedBellmanLoss``'s greedy maximiser) and
    the policy greedy in Q. No actor: an actor over the one-hot box ``[0, 1]^n`` maximises Q off the data's one-hot
    actions, where Q is unconstrained. Targets by ``SoftUpdate`` after every step (``q.target_tau``), or residual gradient (``q.bootstrap``)."""
    qc = ctx.cfg.q
    for key, value in (("q.bc_alpha", qc.bc_alpha), ("q.weight_actor_loss", qc.weight_actor_loss),
                       ("q.expert_bc_weighted_d", qc.expert_bc_weighted_d),
                       ("q.expert_bc_from_d", qc.expert_bc_from_d)):
        if value:
            raise ValueError(f"{key}={value!r} configures the actor, but a Discrete({num_actions}) action has none "
                             f"(Q over the {num_actions} actions, the policy greedy in Q): unset {key}.")
    head = make_discrete_q_network(ctx.observation_dim, num_actions, action_space="one-hot",
                                   **critic_options(ctx)).to(ctx.device)
    loss = WeightedBellmanLoss(head, residual=qc.residual, delay_value=qc.bootstrap == "target",
                               residual_gradient=qc.bootstrap == "residual_gradient", use_weights=weighted)
    loss.make_value_estimator(gamma=ctx.gamma)
    updater = ForeachSoftUpdate(loss, tau=qc.target_tau) if qc.bootstrap == "target" else None
    optimisers = {"value": adam(loss.value_network_params.values(True, True), qc.lr)}
    return Algo(loss=loss, optimisers=optimisers,
                step=bellman_step(loss, optimisers, ctx.cfg, updater=updater, every_step=True),
                policy=head, bellman_loss=loss, uses_ratio=weighted)


def check_positive(settings, key: str, *names: str) -> None:
    """``ValueError`` naming ``<key>.<name>`` for the first of ``names`` whose value in ``settings`` is not > 0."""
    for name in names:
        value = getattr(settings, name)
        if not value > 0:
            raise ValueError(f"{key}.{name} must be > 0, got {value!r}.")
