"""The WBRM losses: the robust density-ratio loss (stage 1) and the weighted Bellman residual (stage 2)."""
from __future__ import annotations

from torchrl_wbrm.objectives.mabo import ADVERSARIES, MABOLoss, average_bellman_residual, linear_adversary_weight
from torchrl_wbrm.objectives.robust_density_ratio import (
    RobustDensityRatioLoss,
    basu_power_divergence,
    power_divergence_integrands,
)
from torchrl_wbrm.objectives.weighted_bellman import RESIDUALS, WeightedBellmanLoss, weighted_bellman_residual

__all__ = [
    "ADVERSARIES",
    "MABOLoss",
    "average_bellman_residual",
    "linear_adversary_weight",
    "RESIDUALS",
    "WeightedBellmanLoss",
    "weighted_bellman_residual",
    "RobustDensityRatioLoss",
    "basu_power_divergence",
    "power_divergence_integrands",
]
