"""Fitted Q iteration (D. Ernst, P. Geurts and L. Wehenkel, "Tree-based batch mode reinforcement learning",
JMLR 2005), with a neural regressor."""
from __future__ import annotations

from dataclasses import dataclass

from torchrl.objectives import HardUpdate

from torchrl_wbrm.algos.base import (Algo, AlgoContext, bellman_step, check_positive, critic_actor_optimisers,
                                    deterministic_actor, q_network, q_reader)
from torchrl_wbrm.algos.registry import register_algo
from torchrl_wbrm.objectives import WeightedBellmanLoss


@dataclass
class FQIConfig:
    """Fitted Q iteration (``baselines.fqi``): regress Q onto a frozen target for ``target_update_every`` steps
    (``HardUpdate``), then refresh the target."""

    target_update_every: int = 50


def _check(settings: FQIConfig, key: str) -> None:
    check_positive(settings, key, "target_update_every")


@register_algo("fqi", config=FQIConfig, validate=_check, bellman_residual=True,
               loss="`WeightedBellmanLoss` unweighted + `HardUpdate`",
               reference="Ernst et al. 2005", loss_title="fitted Q iteration: regression loss")
def build_fqi(ctx: AlgoContext) -> Algo:
    """The unweighted squared Bellman residual against a *frozen* target Q (``WeightedBellmanLoss`` with
    ``use_weights=False, delay_value=True``): for ``baselines.fqi.target_update_every`` = K steps Q regresses onto
    r + γ max Q_k(x', ·), then ``HardUpdate`` sets Q_{k+1} = Q. The max is the actor's, as in ``wbrm``.
    """
    qc = ctx.cfg.q
    value_network, actor = q_network(ctx), deterministic_actor(ctx)
    loss = WeightedBellmanLoss(value_network, actor_network=actor, residual="squared", delay_value=True,
                               use_weights=False, maximiser=qc.maximiser, action_spec=ctx.action_spec,
                               num_action_samples=qc.num_action_samples, bc_alpha=qc.bc_alpha or None)
    loss.make_value_estimator(gamma=ctx.gamma)
    updater = HardUpdate(loss, value_network_update_interval=ctx.cfg.baselines.fqi.target_update_every)
    optimisers = critic_actor_optimisers(loss, ctx.cfg)
    return Algo(loss=loss, optimisers=optimisers, step=bellman_step(loss, optimisers, ctx.cfg, updater=updater,
                                                                    every_step=True),
                policy=actor, q_value=q_reader(loss.value_network, loss.value_network_params), bellman_loss=loss)
