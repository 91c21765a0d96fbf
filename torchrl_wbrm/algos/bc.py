"""Behaviour cloning of the expert's actions in S^e (a reference, not offline RL)."""
from __future__ import annotations

import warnings

from tensordict import TensorDictBase
from torchrl.objectives import BCLoss

from torchrl_wbrm.algos.base import Algo, AlgoContext, adam, descend, deterministic_actor
from torchrl_wbrm.algos.registry import register_algo


@register_algo("bc", loss="torchrl `BCLoss` on S^e", reference="behaviour cloning of the expert",
               loss_title="behaviour cloning loss")
def build_bc(ctx: AlgoContext) -> Algo:
    """Behaviour cloning of the expert's actions in S^e (torchrl ``BCLoss``, L2): a reference, not offline RL.
    Budget: ``q.steps``, ``q.actor_lr``."""
    actor = deterministic_actor(ctx)
    with warnings.catch_warnings():  # torchrl's BCLoss lacks the annotation its convert_to_functional asks for
        warnings.filterwarnings("ignore", message="The name target_actor_network_params wasn't part of the annotations",
                                category=UserWarning)
        loss = BCLoss(actor, loss_function="l2")
    optimisers = {"actor": adam(loss.actor_network_params.values(True, True), ctx.cfg.q.actor_lr)}

    def step(batch: TensorDictBase, i: int) -> dict:
        loss_bc = loss(batch)["loss_bc"]
        descend(loss_bc, optimisers["actor"])
        return {"loss_bc": loss_bc.detach()}

    return Algo(loss=loss, optimisers=optimisers, step=step, policy=actor, data="expert")
