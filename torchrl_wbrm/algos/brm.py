"""Unweighted BRM: WBRM's stage 2 with w ≡ 1 and no stage 1."""
from __future__ import annotations

from torchrl_wbrm.algos.base import Algo, AlgoContext, bellman_residual_algo
from torchrl_wbrm.algos.registry import register_algo


@register_algo("brm", bellman_residual=True, clones_expert=True, loss="`WeightedBellmanLoss` with w ≡ 1 (no stage 1)",
               reference="the ablation: what the ratio buys", loss_title="unweighted Bellman residual (w ≡ 1)")
def build_brm(ctx: AlgoContext) -> Algo:
    """Unweighted BRM: WBRM's stage 2 with w ≡ 1 and no stage 1, the ablation that isolates what the ratio buys
    (identical networks, residual, bootstrap, actor and budget; the same as ``algo=wbrm ratio.source=none``)."""
    return bellman_residual_algo(ctx, weighted=False)
