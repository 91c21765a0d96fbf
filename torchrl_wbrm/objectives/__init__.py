"""The WBRM losses: the robust density-ratio loss (stage 1), the weighted Bellman residual (stage 2), and
:class:`WeightedLoss`, ŵ as the per-sample weight of any TorchRL loss."""
from __future__ import annotations

from torchrl_wbrm.objectives.mabo import ADVERSARIES, MABOLoss, average_bellman_residual, linear_adversary_weight
from torchrl_wbrm.objectives.robust_density_ratio import (
    RobustDensityRatioLoss,
    basu_power_divergence,
    power_divergence_integrands,
)
from torchrl_wbrm.objectives.weighted_bellman import RESIDUALS, WeightedBellmanLoss, weighted_bellman_residual
from torchrl_wbrm.objectives.weighted_loss import NATIVE_PRIORITY_WEIGHT_LOSSES, WeightedLoss, reads_priority_weight

__all__ = [
    "ADVERSARIES",
    "MABOLoss",
    "average_bellman_residual",
    "linear_adversary_weight",
    "RESIDUALS",
    "WeightedBellmanLoss",
    "weighted_bellman_residual",
    "NATIVE_PRIORITY_WEIGHT_LOSSES",
    "WeightedLoss",
    "reads_priority_weight",
    "RobustDensityRatioLoss",
    "basu_power_divergence",
    "power_divergence_integrands",
]
