"""Every method the trainer runs, as a configuration of one loop: a loss, its optimisers and a step function.

``build_algo(name, context)`` returns an :class:`Algo`. The trainer samples a batch from the algo's buffer (D, or
S^e for behaviour cloning), calls ``algo.step(batch, step)`` inside its one loop
(:meth:`~torchrl_wbrm.training.WBRMTrainer._run_stage`) and evaluates ``algo.policy`` (under
``set_exploration_type(DETERMINISTIC)``: a stochastic actor acts by its mode) and, where the method has a
``Q(x, a)`` network, ``algo.q_value`` against the exact Q*. No algorithm has a loop of its own.

Every method gets the same data, the same network widths (``q.num_cells``, ``q.actor_num_cells``), the same
optimiser (Adam, ``q.lr`` for critics, ``q.actor_lr`` for actors), batch size, step budget, γ, target rate
``q.target_tau`` and the same output bias of Q (mean(r) / (1 − γ), ``q.init_bias``). Their own settings are under
``baselines.<name>`` (:class:`~torchrl_wbrm.training.config.BaselinesConfig`).

=========  ==================================================  ====================================================
algo       loss                                                 reference
=========  ==================================================  ====================================================
``wbrm``   :class:`~torchrl_wbrm.objectives.WeightedBellmanLoss` the paper
``brm``    ``WeightedBellmanLoss`` with w ≡ 1 (no stage 1)       the ablation: what the ratio buys
``bc``     torchrl ``BCLoss`` on S^e                            behaviour cloning of the expert
``td3bc``  torchrl ``TD3BCLoss`` (two Q networks)               Fujimoto & Gu 2021
``ddpg``   torchrl ``DDPGLoss``                                 Lillicrap et al. 2016
``cql``    torchrl ``CQLLoss``, TanhNormal actor                Kumar et al. 2020
``iql``    torchrl ``IQLLoss``, TanhNormal actor, V network     Kostrikov et al. 2022
``dqn``    torchrl ``DQNLoss`` on the discretised action box    Mnih et al. 2015
``fqi``    ``WeightedBellmanLoss`` unweighted + ``HardUpdate``  Ernst et al. 2005
``mabo``   :class:`~torchrl_wbrm.objectives.MABOLoss`           Xie & Jiang 2020
=========  ==================================================  ====================================================

To add a method: write ``build_<name>(context) -> Algo`` here, add it to :data:`ALGOS`, add ``<name>`` to the
``algo`` choices of :func:`~torchrl_wbrm.training.config.validate_config` and a ``configs/algo/<name>.yaml``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torchrl.data import Bounded
from torchrl.modules import ValueOperator
from torchrl.objectives import (
    BCLoss,
    CQLLoss,
    DDPGLoss,
    DQNLoss,
    HardUpdate,
    IQLLoss,
    LossModule,
    SoftUpdate,
    TD3BCLoss,
)

from torchrl_wbrm.policies import make_mountain_car_env
from torchrl_wbrm.modules import ActionGrid  # re-exported here (it lived here before modules/)
from torchrl_wbrm.modules import (
    PolynomialFeatures,
    build_mlp,
    make_deterministic_actor,
    make_discrete_q_network,
    make_q_network,
    make_tanh_normal_actor,
)
from torchrl_wbrm.objectives import MABOLoss, WeightedBellmanLoss
from torchrl_wbrm.objectives._fast import ForeachSoftUpdate  # torchrl's SoftUpdate, one foreach lerp per step
from torchrl_wbrm.training.config import WBRMConfig

__all__ = [
    "ALGOS",
    "Algo",
    "AlgoContext",
    "ActionGrid",
    "build_algo",
    "make_tanh_normal_actor",
]

StepFn = Callable[[TensorDictBase, int], dict]
QValueFn = Callable[[TensorDictBase], "tuple[torch.Tensor, torch.Tensor]"]


@dataclass
class AlgoContext:
    """What a builder needs from the trainer: the config, the problem's sizes, the Q output bias and (with
    ``q.normalise_observations``) the data's observation mean and standard deviation for the networks' input."""

    cfg: WBRMConfig
    observation_dim: int
    action_dim: int
    action_spec: Bounded
    gamma: float
    q_initial_bias: float
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    observation_loc: torch.Tensor | None = None
    observation_scale: torch.Tensor | None = None


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


# ---------------------------------------------------------------------- shared pieces
def _descend(loss: torch.Tensor, optimiser: torch.optim.Optimizer, grad_clip: float | None = None) -> None:
    """One gradient step of ``optimiser`` on ``loss`` (optionally clipping the gradient norm of its parameters)."""
    optimiser.zero_grad(set_to_none=True)
    loss.backward()
    if grad_clip:
        params = [p for group in optimiser.param_groups for p in group["params"]]
        torch.nn.utils.clip_grad_norm_(params, grad_clip)
    optimiser.step()


def _descend_all(losses: dict[str, torch.Tensor], optimisers: dict[str, torch.optim.Optimizer]) -> None:
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
    per parameter instead of a dozen (Adam took 0.6 ms of a 2×256 critic step on CPU, fused 0.3 ms). It changes the
    update only in floating-point order (≤ 1 ulp per step against the default for-loop Adam)."""
    params = list(params)
    ok = bool(params) and all(p.is_floating_point() and p.device.type in ("cpu", "cuda") for p in params)
    return {"fused": True} if ok else {}


def _adam(params, lr: float) -> torch.optim.Adam:
    params = list(params)
    return torch.optim.Adam(params, lr=lr, **adam_options(params))


def _critic_actor_optimisers(loss: LossModule, cfg: WBRMConfig, critic: str = "value") -> dict[str, torch.optim.Optimizer]:
    """Adam for the loss's ``<critic>_network_params`` (``q.lr``) and ``actor_network_params`` (``q.actor_lr``), named
    ``critic`` and ``"actor"`` (the names are checkpoint keys)."""
    return {
        critic: _adam(getattr(loss, f"{critic}_network_params").values(True, True), cfg.q.lr),
        "actor": _adam(loss.actor_network_params.values(True, True), cfg.q.actor_lr),
    }


def _scalars(figures: dict | TensorDictBase) -> dict:
    return {k: v.detach() for k, v in figures.items() if isinstance(v, torch.Tensor) and v.ndim == 0}


def _q_reader(network: TensorDictModuleBase, params, value_key="state_action_value") -> QValueFn:
    """Q̂(x, a) of a continuous-action Q network loaded with ``params`` (the first member of an ensemble)."""

    def q_value(td: TensorDictBase):
        with params.to_module(network):
            q = network(td.select(*network.in_keys).clone())[value_key]
        return q.reshape(-1), td["action"]

    return q_value


def _critic_options(ctx: AlgoContext) -> dict:
    """The network options of every critic (Q, V, DQN's head): ``q.num_cells``, ``q.activation``, ``q.layer_norm``,
    the ensemble, ``q.value_scale``, the output bias and the input normalisation."""
    qc = ctx.cfg.q
    return dict(num_cells=qc.num_cells, activation=qc.activation, layer_norm=qc.layer_norm,
                initial_bias=ctx.q_initial_bias, num_members=qc.ensemble_size,
                ensemble_reduction=qc.ensemble_reduction, value_scale=qc.value_scale,
                observation_loc=ctx.observation_loc, observation_scale=ctx.observation_scale)


def _actor_options(ctx: AlgoContext) -> dict:
    """The network options of every actor: ``q.actor_num_cells``, ``q.actor_activation``, ``q.actor_layer_norm`` and
    the input normalisation."""
    qc = ctx.cfg.q
    return dict(num_cells=qc.actor_num_cells, activation=qc.actor_activation, layer_norm=qc.actor_layer_norm,
                observation_loc=ctx.observation_loc, observation_scale=ctx.observation_scale)


def _q_network(ctx: AlgoContext) -> ValueOperator:
    return make_q_network(ctx.observation_dim, ctx.action_dim, **_critic_options(ctx)).to(ctx.device)


def _deterministic_actor(ctx: AlgoContext):
    return make_deterministic_actor(ctx.observation_dim, ctx.action_spec, **_actor_options(ctx)).to(ctx.device)


def _bellman_step(loss: WeightedBellmanLoss, optimisers, cfg: WBRMConfig, *, updater=None, every_step=False) -> StepFn:
    """The step of the Bellman-residual family (wbrm, fqi): a Q step, and every ``q.actor_delay`` steps an actor step.

    ``updater`` is stepped after each actor step (``SoftUpdate``) or, with ``every_step``, after every Q step
    (``HardUpdate`` counts calls and copies every K of them).

    With ``q.compile`` the two losses are :class:`~torchrl_wbrm.objectives._compiled.CompiledBellmanLosses` (the same
    figures, computed by ``torch.compile``d functions); the optimisers and the updater stay as they are. The step
    function then carries them as ``step.compiled`` (its ``compile_seconds``).
    """
    qc = cfg.q
    losses = loss
    if getattr(qc, "compile", False):
        from torchrl_wbrm.objectives._compiled import CompiledBellmanLosses

        losses = CompiledBellmanLosses(loss)

    def step(batch: TensorDictBase, i: int) -> dict:
        loss_value, figures = losses.value_loss(batch)
        _descend(loss_value, optimisers["value"], qc.grad_clip)
        out = {"loss_value": loss_value.detach(), **_scalars(figures)}
        if updater is not None and every_step:
            updater.step()
        if i % qc.actor_delay == 0 and loss.has_actor:
            loss_actor, _ = losses.actor_loss(batch)
            _descend(loss_actor, optimisers["actor"])
            out["loss_actor"] = loss_actor.detach()
            if updater is not None and not every_step:
                updater.step()
        return out

    step.compiled = losses if losses is not loss else None
    return step


# ---------------------------------------------------------------------- the paper and its references
def _bellman_residual(ctx: AlgoContext, *, weighted: bool) -> Algo:
    """The Bellman-residual family of the paper (``wbrm``, ``brm``): Q by the (weighted) residual, an actor as the
    maximiser, targets by ``SoftUpdate`` or residual gradient (``q.bootstrap``)."""
    qc = ctx.cfg.q
    value_network, actor = _q_network(ctx), _deterministic_actor(ctx)
    loss = WeightedBellmanLoss(
        value_network,
        actor_network=actor,
        residual=qc.residual,
        delay_value=qc.bootstrap == "target",
        use_weights=weighted,
        maximiser=qc.maximiser,
        action_spec=ctx.action_spec,
        num_action_samples=qc.num_action_samples,
        weight_actor_loss=qc.weight_actor_loss,
        bc_alpha=qc.bc_alpha,
    )
    loss.make_value_estimator(gamma=ctx.gamma)
    updater = ForeachSoftUpdate(loss, tau=qc.target_tau) if qc.bootstrap == "target" else None
    optimisers = _critic_actor_optimisers(loss, ctx.cfg)
    return Algo(
        loss=loss,
        optimisers=optimisers,
        step=_bellman_step(loss, optimisers, ctx.cfg, updater=updater),
        policy=actor,
        q_value=_q_reader(loss.value_network, loss.value_network_params),
        bellman_loss=loss,
        uses_ratio=weighted,
    )


def build_wbrm(ctx: AlgoContext) -> Algo:
    """WBRM stage 2: the ŵ-weighted Bellman residual (``ratio.source=none``: weights ≡ 1, the same as ``brm``)."""
    return _bellman_residual(ctx, weighted=ctx.cfg.ratio.source != "none")


def build_brm(ctx: AlgoContext) -> Algo:
    """Unweighted BRM: WBRM's stage 2 with w ≡ 1 and no stage 1, the ablation that isolates what the ratio buys
    (identical networks, residual, bootstrap, actor and budget)."""
    return _bellman_residual(ctx, weighted=False)


def build_bc(ctx: AlgoContext) -> Algo:
    """Behaviour cloning of the expert's actions in S^e (torchrl ``BCLoss``, L2): a reference, not offline RL."""
    actor = _deterministic_actor(ctx)
    loss = BCLoss(actor, loss_function="l2")
    optimisers = {"actor": _adam(loss.actor_network_params.values(True, True), ctx.cfg.q.actor_lr)}

    def step(batch: TensorDictBase, i: int) -> dict:
        loss_bc = loss(batch)["loss_bc"]
        _descend(loss_bc, optimisers["actor"])
        return {"loss_bc": loss_bc.detach()}

    return Algo(loss=loss, optimisers=optimisers, step=step, policy=actor, data="expert")


# ---------------------------------------------------------------------- deterministic actor-critic baselines
def build_td3bc(ctx: AlgoContext) -> Algo:
    """TD3+BC (S. Fujimoto and S. S. Gu, "A minimalist approach to offline reinforcement learning", NeurIPS 2021).

    torchrl's ``TD3BCLoss`` with two Q networks (TorchRL copies the Q network into a 2-member ensemble and re-draws
    the copies' weights; the output bias stays at mean(r)/(1 − γ)), target policy smoothing, the actor (and the
    targets, ``SoftUpdate``) every ``q.actor_delay`` critic steps.
    """
    qc, bc = ctx.cfg.q, ctx.cfg.baselines.td3bc
    actor = _deterministic_actor(ctx)
    loss = TD3BCLoss(
        actor, _q_network(ctx), action_spec=ctx.action_spec, num_qvalue_nets=2, alpha=bc.alpha,
        policy_noise=bc.policy_noise, noise_clip=bc.noise_clip, loss_function=bc.loss_function,
    )
    loss.make_value_estimator(gamma=ctx.gamma)
    updater = SoftUpdate(loss, tau=qc.target_tau)
    optimisers = _critic_actor_optimisers(loss, ctx.cfg, critic="qvalue")

    def step(batch: TensorDictBase, i: int) -> dict:
        loss_qvalue, _ = loss.qvalue_loss(batch)
        _descend(loss_qvalue, optimisers["qvalue"], qc.grad_clip)
        out = {"loss_qvalue": loss_qvalue.detach()}
        if i % qc.actor_delay == 0:
            loss_actor, figures = loss.actor_loss(batch)
            _descend(loss_actor, optimisers["actor"])
            out.update(loss_actor=loss_actor.detach(), bc_loss=figures["bc_loss"])
            updater.step()
        return out

    return Algo(loss=loss, optimisers=optimisers, step=step, policy=actor,
                q_value=_q_reader(loss.qvalue_network, loss.qvalue_network_params[0]))


def build_ddpg(ctx: AlgoContext) -> Algo:
    """Offline DDPG (T. P. Lillicrap et al., "Continuous control with deep reinforcement learning", ICLR 2016).

    torchrl's ``DDPGLoss``: Q regressed on r + γ Q'(x', μ'(x')) with target copies of Q and μ (``SoftUpdate``),
    μ ascending Q; both updated every step, as in the paper. No constraint keeps μ near the data.
    """
    qc = ctx.cfg.q
    actor = _deterministic_actor(ctx)
    loss = DDPGLoss(actor, _q_network(ctx), loss_function=ctx.cfg.baselines.ddpg.loss_function,
                    delay_actor=True, delay_value=True)
    loss.make_value_estimator(gamma=ctx.gamma)
    updater = SoftUpdate(loss, tau=qc.target_tau)
    optimisers = _critic_actor_optimisers(loss, ctx.cfg)

    def step(batch: TensorDictBase, i: int) -> dict:
        loss_value, _ = loss.loss_value(batch)
        _descend(loss_value, optimisers["value"], qc.grad_clip)
        loss_actor, _ = loss.loss_actor(batch)
        _descend(loss_actor, optimisers["actor"])
        updater.step()
        return {"loss_value": loss_value.detach(), "loss_actor": loss_actor.detach()}

    return Algo(loss=loss, optimisers=optimisers, step=step, policy=actor,
                q_value=_q_reader(loss.value_network, loss.value_network_params))


# ---------------------------------------------------------------------- stochastic actor baselines
def build_cql(ctx: AlgoContext) -> Algo:
    """CQL(H) (A. Kumar, A. Zhou, G. Tucker and S. Levine, "Conservative Q-learning for offline reinforcement
    learning", NeurIPS 2020), continuous actions.

    torchrl's ``CQLLoss``: SAC's losses plus the conservative penalty log Σ exp Q − Q(data), two Q networks, a
    TanhNormal actor (evaluated by its mode), entropy coefficient tuned. All losses are summed and stepped at once,
    as torchrl's ``cql_offline`` does. Note: TorchRL draws CQL's uniform actions in [−1, 1]ᵐ, not in the action
    spec's box, so with LQR's box [−5, 5]² they cover its centre only.
    """
    qc, cc = ctx.cfg.q, ctx.cfg.baselines.cql
    actor = make_tanh_normal_actor(ctx.observation_dim, ctx.action_spec, **_actor_options(ctx)).to(ctx.device)
    loss = CQLLoss(
        actor, _q_network(ctx), action_spec=ctx.action_spec, loss_function=cc.loss_function,
        alpha_init=cc.alpha_init, temperature=cc.temperature, min_q_weight=cc.min_q_weight,
        num_random=cc.num_random, with_lagrange=cc.with_lagrange, lagrange_thresh=cc.lagrange_thresh,
    )
    loss.make_value_estimator(gamma=ctx.gamma)
    updater = SoftUpdate(loss, tau=qc.target_tau)
    optimisers = {**_critic_actor_optimisers(loss, ctx.cfg, critic="qvalue"), "alpha": _adam([loss.log_alpha], qc.actor_lr)}
    if cc.with_lagrange:
        optimisers["alpha_prime"] = _adam([loss.log_alpha_prime], qc.lr)

    def step(batch: TensorDictBase, i: int) -> dict:
        out = loss(batch)
        losses = {k: out[k] for k in ("loss_actor", "loss_qvalue", "loss_cql", "loss_alpha", "loss_alpha_prime")
                  if k in out.keys()}
        _descend_all(losses, optimisers)
        updater.step()
        return _scalars(out)

    return Algo(loss=loss, optimisers=optimisers, step=step, policy=actor,
                q_value=_q_reader(loss.qvalue_network, loss.qvalue_network_params[0]))


def build_iql(ctx: AlgoContext) -> Algo:
    """IQL (I. Kostrikov, A. Nair and S. Levine, "Offline reinforcement learning with implicit Q-learning",
    ICLR 2022).

    torchrl's ``IQLLoss``: V by expectile regression on the target Q, Q on r + γ V(x'), the TanhNormal actor by
    advantage-weighted regression on the data's actions (evaluated by its mode); targets by ``SoftUpdate``. V is
    ``make_q_network`` on the observation alone, with Q's output bias.
    """
    qc, ic = ctx.cfg.q, ctx.cfg.baselines.iql
    actor = make_tanh_normal_actor(ctx.observation_dim, ctx.action_spec, **_actor_options(ctx)).to(ctx.device)
    value = make_q_network(ctx.observation_dim, 0, **_critic_options(ctx), in_keys=("observation",),
                           out_key="state_value").to(ctx.device)
    loss = IQLLoss(actor, _q_network(ctx), value, loss_function=ic.loss_function,
                   temperature=ic.temperature, expectile=ic.expectile)
    loss.make_value_estimator(gamma=ctx.gamma)
    updater = SoftUpdate(loss, tau=qc.target_tau)
    optimisers = {**_critic_actor_optimisers(loss, ctx.cfg, critic="qvalue"),
                  "value": _adam(loss.value_network_params.values(True, True), qc.lr)}

    def step(batch: TensorDictBase, i: int) -> dict:
        out = loss(batch)
        _descend_all({k: out[k] for k in ("loss_actor", "loss_qvalue", "loss_value")}, optimisers)
        updater.step()
        return _scalars(out)

    return Algo(loss=loss, optimisers=optimisers, step=step, policy=actor,
                q_value=_q_reader(loss.qvalue_network, loss.qvalue_network_params[0]))


# ---------------------------------------------------------------------- discrete actions
def build_dqn(ctx: AlgoContext) -> Algo:
    """DQN (V. Mnih et al., "Human-level control through deep reinforcement learning", Nature 2015), offline, on the
    discretised action box (LQR: ``num_bins ** 2`` joint actions; MountainCar: ``num_bins``).

    torchrl's ``DQNLoss`` on a Q head over the ``num_bins ** m`` joint actions of :class:`ActionGrid` (categorical
    indices). The dataset's continuous actions are snapped to the nearest grid point once, before they enter the
    buffer; the evaluated policy is the greedy head followed by a module mapping its index back to the continuous
    action, so it runs in the continuous env against the same optimum. Targets by ``SoftUpdate``. The Q* error is
    scored at the grid point nearest to each evaluation action.
    """
    cfg = ctx.cfg
    qc, dc = cfg.q, cfg.baselines.dqn
    if cfg.env.kind == "lqr":
        grid = ActionGrid.from_lqr_env(cfg.env.lqr, dc.num_bins)
    else:
        grid = ActionGrid.from_env(make_mountain_car_env(), dc.num_bins)
    grid = grid.to(ctx.device)
    q_head = make_discrete_q_network(ctx.observation_dim, grid.num_actions, action_space="categorical",
                                     **_critic_options(ctx)).to(ctx.device)
    loss = DQNLoss(q_head, loss_function=dc.loss_function, delay_value=True)
    loss.make_value_estimator(gamma=ctx.gamma)
    updater = SoftUpdate(loss, tau=qc.target_tau)
    optimisers = {"value": _adam(loss.value_network_params.values(True, True), qc.lr)}
    policy = TensorDictSequential(q_head, TensorDictModule(grid, in_keys=["action"], out_keys=["action"]))

    def step(batch: TensorDictBase, i: int) -> dict:
        out = loss(batch)
        _descend(out["loss"], optimisers["value"], qc.grad_clip)
        updater.step()
        return {"loss_value": out["loss"].detach()}

    def map_data(td: TensorDictBase) -> TensorDictBase:
        td = td.clone()
        td.set("continuous_action", td["action"])
        td.del_("action")
        td.set("action", grid.index(td["continuous_action"]))
        return td

    def q_value(td: TensorDictBase):
        index = grid.index(td["action"])
        with loss.value_network_params.to_module(loss.value_network):
            values = loss.value_network(td.select("observation").clone())["action_value"]
        return values.gather(-1, index.unsqueeze(-1)).reshape(-1), grid(index)

    return Algo(loss=loss, optimisers=optimisers, step=step, policy=policy, q_value=q_value, map_data=map_data)


# ---------------------------------------------------------------------- Q* estimators of the paper's comparison
def build_fqi(ctx: AlgoContext) -> Algo:
    """Fitted Q iteration (D. Ernst, P. Geurts and L. Wehenkel, "Tree-based batch mode reinforcement learning",
    JMLR 2005), with a neural regressor.

    The unweighted squared Bellman residual against a *frozen* target Q (``WeightedBellmanLoss`` with
    ``use_weights=False, delay_value=True``): for ``baselines.fqi.target_update_every`` = K steps Q regresses onto
    r + γ max Q_k(x', ·), then ``HardUpdate`` sets Q_{k+1} = Q. The max is the actor's, as in ``wbrm``.
    """
    qc = ctx.cfg.q
    value_network, actor = _q_network(ctx), _deterministic_actor(ctx)
    loss = WeightedBellmanLoss(value_network, actor_network=actor, residual="squared", delay_value=True,
                               use_weights=False, maximiser=qc.maximiser, action_spec=ctx.action_spec,
                               num_action_samples=qc.num_action_samples, bc_alpha=qc.bc_alpha)
    loss.make_value_estimator(gamma=ctx.gamma)
    updater = HardUpdate(loss, value_network_update_interval=ctx.cfg.baselines.fqi.target_update_every)
    optimisers = _critic_actor_optimisers(loss, ctx.cfg)
    return Algo(loss=loss, optimisers=optimisers, step=_bellman_step(loss, optimisers, ctx.cfg, updater=updater,
                                                                     every_step=True),
                policy=actor, q_value=_q_reader(loss.value_network, loss.value_network_params), bellman_loss=loss)


def _mabo_adversary(ctx: AlgoContext, mc) -> TensorDictModule:
    if mc.adversary == "network":
        mlp = build_mlp(ctx.observation_dim + ctx.action_dim, 1, num_cells=mc.critic_num_cells,
                        activation=ctx.cfg.q.activation, layer_norm=ctx.cfg.q.layer_norm)
        return ValueOperator(mlp, in_keys=["observation", "action"], out_keys=["adversary_output"]).to(ctx.device)
    # the linear span of fixed polynomial features of (x, a)
    return TensorDictModule(PolynomialFeatures(mc.features_degree), in_keys=["observation", "action"],
                            out_keys=["adversary_output"])


def build_mabo(ctx: AlgoContext) -> Algo:
    """MABO (T. Xie and N. Jiang, "Q* approximation schemes for batch reinforcement learning: a theoretical
    comparison", UAI 2020): ``min_Q max_{w ∈ W} |E_b[w(x, a) δ]|``, by alternating updates.

    Each step: ``baselines.mabo.critic_steps`` ascent steps of the adversary w (``loss_critic``, critic only), then a
    descent step of Q (``loss_value`` with w fixed), and every ``q.actor_delay`` steps the actor (the max over next
    actions) and, with ``delay_value``, the target (``SoftUpdate``).
    """
    qc, mc = ctx.cfg.q, ctx.cfg.baselines.mabo
    value_network, actor = _q_network(ctx), _deterministic_actor(ctx)
    loss = MABOLoss(value_network, _mabo_adversary(ctx, mc), actor_network=actor, adversary=mc.adversary,
                    w_bound=mc.w_bound, critic_l2=mc.critic_l2, delay_value=mc.delay_value,
                    maximiser=qc.maximiser, action_spec=ctx.action_spec, num_action_samples=qc.num_action_samples,
                    bc_alpha=qc.bc_alpha)
    loss.make_value_estimator(gamma=ctx.gamma)
    updater = ForeachSoftUpdate(loss, tau=qc.target_tau) if mc.delay_value else None
    optimisers = _critic_actor_optimisers(loss, ctx.cfg)
    if mc.adversary == "network":
        optimisers["critic"] = _adam(loss.critic_network_params.values(True, True), mc.critic_lr)
    bellman_step = _bellman_step(loss, optimisers, ctx.cfg, updater=updater)

    def step(batch: TensorDictBase, i: int) -> dict:
        out = {}
        if mc.adversary == "network":
            for _ in range(mc.critic_steps):
                loss_critic, _ = loss.critic_loss(batch)
                _descend(loss_critic, optimisers["critic"])
            out["loss_critic"] = loss_critic.detach()
        out.update(bellman_step(batch, i))
        return out

    return Algo(loss=loss, optimisers=optimisers, step=step, policy=actor,
                q_value=_q_reader(loss.value_network, loss.value_network_params), bellman_loss=loss)


ALGOS: dict[str, Callable[[AlgoContext], Algo]] = {
    "wbrm": build_wbrm,
    "brm": build_brm,
    "bc": build_bc,
    "td3bc": build_td3bc,
    "ddpg": build_ddpg,
    "cql": build_cql,
    "iql": build_iql,
    "dqn": build_dqn,
    "fqi": build_fqi,
    "mabo": build_mabo,
}


def build_algo(name: str, ctx: AlgoContext) -> Algo:
    """The :class:`Algo` named ``name`` (a key of :data:`ALGOS`)."""
    if name not in ALGOS:
        raise ValueError(f"algo={name!r} is not known: choose one of {sorted(ALGOS)}.")
    return ALGOS[name](ctx)
