"""WBRM, the paper's method: stage 1 fits ŵ, stage 2 minimises the ŵ-weighted Bellman residual."""
from __future__ import annotations

from torchrl_wbrm.algos.base import Algo, AlgoContext, bellman_residual_algo
from torchrl_wbrm.algos.registry import register_algo


@register_algo("wbrm", fits_ratio=True, bellman_residual=True, clones_expert=True,
               loss="`WeightedBellmanLoss`, weighted by the stage-1 ŵ", reference="the paper",
               loss_title="stage 2: weighted Bellman residual")
def build_wbrm(ctx: AlgoContext) -> Algo:
    """WBRM stage 2: the ŵ-weighted Bellman residual (``ratio.source=none``: weights ≡ 1, the same as ``brm``)."""
    return bellman_residual_algo(ctx, weighted=ctx.cfg.ratio.source != "none")
