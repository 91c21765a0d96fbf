"""The WBRM losses: the robust density-ratio loss (stage 1), the weighted Bellman residual (stage 2), and
:class:`WeightedLoss`, ŵ as the per-sample weight of any TorchRL loss. Their equations, each implemented once, are
the functions of :mod:`torchrl_wbrm.objectives.functional`."""
from __future__ import annotations

from torchrl_wbrm.objectives import functional
from torchrl_wbrm.objectives._utils import NonFiniteError
from torchrl_wbrm.objectives.functional import (
    RESIDUALS,
    average_bellman_residual,
    basu_power_divergence,
    linear_adversary_weight,
    power_divergence_integrands,
    weighted_bellman_residual,
)
from torchrl_wbrm.objectives.fqe import FQELoss
from torchrl_wbrm.objectives.mabo import ADVERSARIES, MABOLoss
from torchrl_wbrm.objectives.robust_density_ratio import RobustDensityRatioLoss
from torchrl_wbrm.objectives.weighted_bellman import WeightedBellmanLoss
from torchrl_wbrm.objectives.weighted_loss import NATIVE_PRIORITY_WEIGHT_LOSSES, WeightedLoss, reads_priority_weight

__all__ = [
    "functional",
    "NonFiniteError",
    "FQELoss",
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
