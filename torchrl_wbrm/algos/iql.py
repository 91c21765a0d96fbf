"""IQL (I. Kostrikov, A. Nair and S. Levine, "Offline reinforcement learning with implicit Q-learning", ICLR 2022)."""
from __future__ import annotations

from dataclasses import dataclass

from tensordict import TensorDictBase
from torchrl.objectives import IQLLoss, SoftUpdate

from torchrl_wbrm.algos.base import (Algo, AlgoContext, actor_options, adam, check_positive, critic_actor_optimisers,
                                    critic_options, descend_all, q_network, q_reader, scalars)
from torchrl_wbrm.algos.registry import register_algo
from torchrl_wbrm.modules import make_q_network, make_tanh_normal_actor


@dataclass
class IQLConfig:
    """IQL with torchrl's ``IQLLoss`` (``baselines.iql``).

    Attributes:
        expectile: the value's expectile τ, in (0, 1).
        temperature: the inverse temperature β of the advantage weights.
        loss_function: the critics' loss.
    """

    expectile: float = 0.7
    temperature: float = 3.0
    loss_function: str = "l2"


def _check(settings: IQLConfig, key: str) -> None:
    check_positive(settings, key, "temperature")
    if not 0 < settings.expectile < 1:
        raise ValueError(f"{key}.expectile must lie in (0, 1), got {settings.expectile}.")


@register_algo("iql", config=IQLConfig, validate=_check, loss="torchrl `IQLLoss`, TanhNormal actor, V network",
               reference="Kostrikov et al. 2022", loss_title="IQL: losses")
def build_iql(ctx: AlgoContext) -> Algo:
    """torchrl's ``IQLLoss`` on D: V by expectile regression on the target Q, Q on r + γ V(x'), the TanhNormal actor
    by advantage-weighted regression on the data's actions (evaluated by its mode); targets by ``SoftUpdate``. V is
    ``make_q_network`` on the observation alone, with Q's output bias.
    """
    qc, ic = ctx.cfg.q, ctx.cfg.baselines.iql
    actor = make_tanh_normal_actor(ctx.observation_dim, ctx.action_spec, **actor_options(ctx)).to(ctx.device)
    value = make_q_network(ctx.observation_dim, 0, **critic_options(ctx), in_keys=("observation",),
                           out_key="state_value").to(ctx.device)
    loss = IQLLoss(actor, q_network(ctx), value, loss_function=ic.loss_function,
                   temperature=ic.temperature, expectile=ic.expectile)
    loss.make_value_estimator(gamma=ctx.gamma)
    updater = SoftUpdate(loss, tau=qc.target_tau)
    optimisers = {**critic_actor_optimisers(loss, ctx.cfg, critic="qvalue"),
                  "value": adam(loss.value_network_params.values(True, True), qc.lr)}

    def step(batch: TensorDictBase, i: int) -> dict:
        out = loss(batch)
        descend_all({k: out[k] for k in ("loss_actor", "loss_qvalue", "loss_value")}, optimisers)
        updater.step()
        return scalars(out)

    return Algo(loss=loss, optimisers=optimisers, step=step, policy=actor,
                q_value=q_reader(loss.qvalue_network, loss.qvalue_network_params[0]))
