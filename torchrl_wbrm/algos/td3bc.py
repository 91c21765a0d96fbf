"""TD3+BC (S. Fujimoto and S. S. Gu, "A minimalist approach to offline reinforcement learning", NeurIPS 2021)."""
from __future__ import annotations

from dataclasses import dataclass

from tensordict import TensorDictBase
from torchrl.objectives import SoftUpdate, TD3BCLoss

from torchrl_wbrm.algos.base import (Algo, AlgoContext, critic_actor_optimisers, descend, deterministic_actor,
                                    q_network, q_reader)
from torchrl_wbrm.algos.registry import register_algo


@dataclass
class TD3BCConfig:
    """TD3+BC with torchrl's ``TD3BCLoss`` (``baselines.td3bc``).

    Attributes:
        alpha: α of λ = α / mean|Q(x, μ(x))|.
        policy_noise: target policy smoothing, in action units; clipped at ``noise_clip``.
        noise_clip: the clip of the smoothing noise.
        loss_function: the critic's loss (``"l2"``, ``"l1"``, ``"smooth_l1"``).
    """

    alpha: float = 2.5
    policy_noise: float = 0.2
    noise_clip: float = 0.5
    loss_function: str = "l2"


@register_algo("td3bc", config=TD3BCConfig, loss="torchrl `TD3BCLoss` (two Q networks)",
               reference="Fujimoto & Gu 2021", loss_title="TD3+BC: critic and actor losses")
def build_td3bc(ctx: AlgoContext) -> Algo:
    """TD3+BC on D: torchrl's ``TD3BCLoss`` with two Q networks (TorchRL copies the Q network into a 2-member
    ensemble and re-draws the copies' weights; the output bias stays at mean(r)/(1 − γ)), target policy smoothing,
    the actor (and the targets, ``SoftUpdate``) every ``q.actor_delay`` critic steps.
    """
    qc, bc = ctx.cfg.q, ctx.cfg.baselines.td3bc
    actor = deterministic_actor(ctx)
    loss = TD3BCLoss(
        actor, q_network(ctx), action_spec=ctx.action_spec, num_qvalue_nets=2, alpha=bc.alpha,
        policy_noise=bc.policy_noise, noise_clip=bc.noise_clip, loss_function=bc.loss_function,
    )
    loss.make_value_estimator(gamma=ctx.gamma)
    updater = SoftUpdate(loss, tau=qc.target_tau)
    optimisers = critic_actor_optimisers(loss, ctx.cfg, critic="qvalue")

    def step(batch: TensorDictBase, i: int) -> dict:
        loss_qvalue, _ = loss.qvalue_loss(batch)
        descend(loss_qvalue, optimisers["qvalue"], qc.grad_clip)
        out = {"loss_qvalue": loss_qvalue.detach()}
        if i % qc.actor_delay == 0:
            loss_actor, figures = loss.actor_loss(batch)
            descend(loss_actor, optimisers["actor"])
            out.update(loss_actor=loss_actor.detach(), bc_loss=figures["bc_loss"])
            updater.step()
        return out

    return Algo(loss=loss, optimisers=optimisers, step=step, policy=actor,
                q_value=q_reader(loss.qvalue_network, loss.qvalue_network_params[0]))
