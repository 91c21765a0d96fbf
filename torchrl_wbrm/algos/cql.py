"""CQL(H) (A. Kumar, A. Zhou, G. Tucker and S. Levine, "Conservative Q-learning for offline reinforcement learning",
NeurIPS 2020), continuous actions."""
from __future__ import annotations

from dataclasses import dataclass

from tensordict import TensorDictBase
from torchrl.objectives import CQLLoss, SoftUpdate

from torchrl_wbrm.algos.base import (Algo, AlgoContext, actor_options, adam, check_positive, critic_actor_optimisers,
                                    descend_all, q_network, q_reader, scalars)
from torchrl_wbrm.algos.registry import register_algo
from torchrl_wbrm.modules import make_tanh_normal_actor


@dataclass
class CQLConfig:
    """CQL(H) for continuous actions with torchrl's ``CQLLoss`` and a TanhNormal actor (``baselines.cql``).

    Attributes:
        min_q_weight: the conservative penalty's weight (the paper's α).
        temperature: its log-sum-exp temperature.
        num_random: uniform actions per state.
        with_lagrange, lagrange_thresh: the Lagrangian variant.
        alpha_init: the initial entropy coefficient (tuned as in SAC).
        loss_function: the critics' loss.
    """

    min_q_weight: float = 1.0
    temperature: float = 1.0
    num_random: int = 10
    with_lagrange: bool = False
    lagrange_thresh: float = 5.0
    alpha_init: float = 1.0
    loss_function: str = "l2"


def _check(settings: CQLConfig, key: str) -> None:
    check_positive(settings, key, "num_random")


@register_algo("cql", config=CQLConfig, validate=_check, loss="torchrl `CQLLoss`, TanhNormal actor",
               reference="Kumar et al. 2020", loss_title="CQL: losses")
def build_cql(ctx: AlgoContext) -> Algo:
    """torchrl's ``CQLLoss`` on D: SAC's losses plus the conservative penalty log Σ exp Q − Q(data), two Q
    networks, a TanhNormal actor (evaluated by its mode), entropy coefficient tuned. All losses are summed and stepped
    at once, as torchrl's ``cql_offline`` does. Note: TorchRL draws CQL's uniform actions in [−1, 1]ᵐ, not in the
    action spec's box, so with LQR's box [−5, 5]² they cover its centre only.
    """
    qc, cc = ctx.cfg.q, ctx.cfg.baselines.cql
    actor = make_tanh_normal_actor(ctx.observation_dim, ctx.action_spec, **actor_options(ctx)).to(ctx.device)
    loss = CQLLoss(
        actor, q_network(ctx), action_spec=ctx.action_spec, loss_function=cc.loss_function,
        alpha_init=cc.alpha_init, temperature=cc.temperature, min_q_weight=cc.min_q_weight,
        num_random=cc.num_random, with_lagrange=cc.with_lagrange, lagrange_thresh=cc.lagrange_thresh,
    )
    loss.make_value_estimator(gamma=ctx.gamma)
    updater = SoftUpdate(loss, tau=qc.target_tau)
    optimisers = {**critic_actor_optimisers(loss, ctx.cfg, critic="qvalue"), "alpha": adam([loss.log_alpha], qc.actor_lr)}
    if cc.with_lagrange:
        optimisers["alpha_prime"] = adam([loss.log_alpha_prime], qc.lr)

    def step(batch: TensorDictBase, i: int) -> dict:
        out = loss(batch)
        losses = {k: out[k] for k in ("loss_actor", "loss_qvalue", "loss_cql", "loss_alpha", "loss_alpha_prime")
                  if k in out.keys()}
        descend_all(losses, optimisers)
        updater.step()
        return scalars(out)

    return Algo(loss=loss, optimisers=optimisers, step=step, policy=actor,
                q_value=q_reader(loss.qvalue_network, loss.qvalue_network_params[0]))
