"""MABO (T. Xie and N. Jiang, "Q* approximation schemes for batch reinforcement learning: a theoretical comparison",
UAI 2020): ``min_Q max_{w ∈ W} |E_b[w(x, a) δ]|``, by alternating updates."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import List

from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torchrl.modules import ValueOperator

from torchrl_wbrm.algos.base import (Algo, AlgoContext, adam, bellman_step, check_positive, critic_actor_optimisers,
                                    descend, deterministic_actor, q_network, q_reader)
from torchrl_wbrm.algos.registry import register_algo
from torchrl_wbrm.modules import PolynomialFeatures, build_mlp
from torchrl_wbrm.objectives import MABOLoss
from torchrl_wbrm.objectives._fast import ForeachSoftUpdate

ADVERSARIES = ("network", "linear")


@dataclass
class MABOConfig:
    """MABO with :class:`~torchrl_wbrm.objectives.MABOLoss` (``baselines.mabo``). The defaults are the variant that
    did least badly on the LQR tasks (:doc:`/results/paper_tables`).

    Attributes:
        adversary: the adversary class W: ``"linear"`` (the span of
            :class:`~torchrl_wbrm.modules.PolynomialFeatures` of degree ``features_degree``, ‖θ‖ ≤ ``w_bound``, exact
            inner max) or ``"network"`` (``B·tanh`` of an MLP trained by ascent).
        features_degree: linear: 1 -> (1, x, a); 2 -> also every x_i x_j, x_i a_j, a_i a_j.
        w_bound: the adversary's bound B.
        critic_l2: network: an L2 penalty on w (> 0 turns the inner max into a squared error).
        critic_lr, critic_num_cells: network only: the adversary's learning rate and widths.
        critic_steps: network only: ascent steps per Q step.
        delay_value: a frozen target Q (``SoftUpdate``) rather than the paper's gradient through both Q terms.
    """

    adversary: str = "linear"
    features_degree: int = 2
    w_bound: float = 1.0
    critic_l2: float = 0.0
    critic_lr: float = 1e-3
    critic_num_cells: List[int] = field(default_factory=lambda: [256, 256])
    critic_steps: int = 1
    delay_value: bool = True


def _check(settings: MABOConfig, key: str) -> None:
    if settings.adversary not in ADVERSARIES:
        raise ValueError(f"{key}.adversary={settings.adversary!r} is not allowed: choose one of {list(ADVERSARIES)}.")
    check_positive(settings, key, "w_bound", "critic_lr", "critic_steps")
    if settings.features_degree not in (1, 2):
        raise ValueError(f"{key}.features_degree must be 1 or 2, got {settings.features_degree!r}.")


def _adversary(ctx: AlgoContext, mc: MABOConfig) -> TensorDictModule:
    if mc.adversary == "network":
        mlp = build_mlp(ctx.observation_dim + ctx.action_dim, 1, num_cells=mc.critic_num_cells,
                        activation=ctx.cfg.q.activation, layer_norm=ctx.cfg.q.layer_norm)
        return ValueOperator(mlp, in_keys=["observation", "action"], out_keys=["adversary_output"]).to(ctx.device)
    # the linear span of fixed polynomial features of (x, a)
    return TensorDictModule(PolynomialFeatures(mc.features_degree), in_keys=["observation", "action"],
                            out_keys=["adversary_output"])


@register_algo("mabo", config=MABOConfig, validate=_check, bellman_residual=True, loss="`MABOLoss`",
               reference="Xie & Jiang 2020", loss_title="MABO: Bellman loss against the adversary")
def build_mabo(ctx: AlgoContext) -> Algo:
    """Each step: ``baselines.mabo.critic_steps`` ascent steps of the adversary w (``loss_critic``, critic only),
    then a descent step of Q (``loss_value`` with w fixed), and every ``q.actor_delay`` steps the actor (the max over
    next actions) and, with ``delay_value``, the target (``SoftUpdate``).
    """
    qc, mc = ctx.cfg.q, ctx.cfg.baselines.mabo
    value_network, actor = q_network(ctx), deterministic_actor(ctx)
    loss = MABOLoss(value_network, _adversary(ctx, mc), actor_network=actor, adversary=mc.adversary,
                    w_bound=mc.w_bound, critic_l2=mc.critic_l2, delay_value=mc.delay_value,
                    maximiser=qc.maximiser, action_spec=ctx.action_spec, num_action_samples=qc.num_action_samples,
                    bc_alpha=qc.bc_alpha or None)
    loss.make_value_estimator(gamma=ctx.gamma)
    updater = ForeachSoftUpdate(loss, tau=qc.target_tau) if mc.delay_value else None
    optimisers = critic_actor_optimisers(loss, ctx.cfg)
    if mc.adversary == "network":
        optimisers["critic"] = adam(loss.critic_network_params.values(True, True), mc.critic_lr)
    q_step = bellman_step(loss, optimisers, ctx.cfg, updater=updater)

    def step(batch: TensorDictBase, i: int) -> dict:
        out = {}
        if mc.adversary == "network":
            for _ in range(mc.critic_steps):
                loss_critic, _ = loss.critic_loss(batch)
                descend(loss_critic, optimisers["critic"])
            out["loss_critic"] = loss_critic.detach()
        out.update(q_step(batch, i))
        return out

    return Algo(loss=loss, optimisers=optimisers, step=step, policy=actor,
                q_value=q_reader(loss.value_network, loss.value_network_params), bellman_loss=loss)
