"""Offline DDPG (T. P. Lillicrap et al., "Continuous control with deep reinforcement learning", ICLR 2016)."""
from __future__ import annotations

from dataclasses import dataclass

from tensordict import TensorDictBase
from torchrl.objectives import DDPGLoss, SoftUpdate

from torchrl_wbrm.algos.base import (Algo, AlgoContext, critic_actor_optimisers, descend, deterministic_actor,
                                    q_network, q_reader)
from torchrl_wbrm.algos.registry import register_algo


@dataclass
class DDPGConfig:
    """Offline DDPG with torchrl's ``DDPGLoss`` (``baselines.ddpg``): the critic's ``loss_function``."""

    loss_function: str = "l2"


@register_algo("ddpg", config=DDPGConfig, critic_layer_norm=True, loss="torchrl `DDPGLoss`",
               reference="Lillicrap et al. 2016", loss_title="DDPG: critic and actor losses")
def build_ddpg(ctx: AlgoContext) -> Algo:
    """torchrl's ``DDPGLoss`` on D: Q regressed on r + γ Q'(x', μ'(x')) with target copies of Q and μ
    (``SoftUpdate(q.target_tau)``), μ ascending Q; both updated every step, as in the paper. No constraint keeps μ
    near the data.

    Where the task's default puts a LayerNorm in Q (Minari datasets with a continuous action), DDPG's critic gets it
    too (:attr:`~torchrl_wbrm.algos.AlgoSpec.critic_layer_norm`): offline, nothing else bounds Q at the actions μ
    picks off the data; without it Q̂ grows past r_max / (1 − γ) (flagged ``q_blow_up``;
    :doc:`/results/benchmark`).
    """
    qc = ctx.cfg.q
    actor = deterministic_actor(ctx)
    loss = DDPGLoss(actor, q_network(ctx), loss_function=ctx.cfg.baselines.ddpg.loss_function,
                    delay_actor=True, delay_value=True)
    loss.make_value_estimator(gamma=ctx.gamma)
    updater = SoftUpdate(loss, tau=qc.target_tau)
    optimisers = critic_actor_optimisers(loss, ctx.cfg)

    def step(batch: TensorDictBase, i: int) -> dict:
        loss_value, _ = loss.loss_value(batch)
        descend(loss_value, optimisers["value"], qc.grad_clip)
        loss_actor, _ = loss.loss_actor(batch)
        descend(loss_actor, optimisers["actor"])
        updater.step()
        return {"loss_value": loss_value.detach(), "loss_actor": loss_actor.detach()}

    return Algo(loss=loss, optimisers=optimisers, step=step, policy=actor,
                q_value=q_reader(loss.value_network, loss.value_network_params))
