"""Network builders: Q networks, fixed polynomial features, a bounded actor, the positive bounded density-ratio network,
action maximisers, the action grid of a discretised box."""
from __future__ import annotations

from torchrl_wbrm.modules.action_grid import ActionGrid
from torchrl_wbrm.modules.density_ratio import (
    DEFAULT_PARAMETERISATION,
    PARAMETERISATIONS,
    BoundedRatio,
    DensityRatioNetwork,
)
from torchrl_wbrm.modules.features import PolynomialFeatures
from torchrl_wbrm.modules.maximisers import (
    ActionMaximiser,
    ActorMaximiser,
    GreedyDiscreteMaximiser,
    SampledActionMaximiser,
    max_q_over_candidates,
    uniform_actions,
)
from torchrl_wbrm.modules.networks import (
    ACTIVATIONS,
    BoundedTanh,
    EnsembleReduction,
    NormalisedMLP,
    build_mlp,
    initial_q_value,
    resolve_activation,
    make_deterministic_actor,
    make_discrete_q_network,
    make_q_network,
    make_tanh_normal_actor,
)

__all__ = [
    "ACTIVATIONS",
    "ActionGrid",
    "ActionMaximiser",
    "EnsembleReduction",
    "NormalisedMLP",
    "build_mlp",
    "initial_q_value",
    "resolve_activation",
    "ActorMaximiser",
    "BoundedRatio",
    "BoundedTanh",
    "DEFAULT_PARAMETERISATION",
    "DensityRatioNetwork",
    "GreedyDiscreteMaximiser",
    "PARAMETERISATIONS",
    "PolynomialFeatures",
    "SampledActionMaximiser",
    "make_deterministic_actor",
    "make_discrete_q_network",
    "make_q_network",
    "make_tanh_normal_actor",
    "max_q_over_candidates",
    "uniform_actions",
]
