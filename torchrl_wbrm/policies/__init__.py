"""Expert and behaviour policies (TensorDictModules a torchrl Collector can run)."""
from torchrl_wbrm.policies.lqr import (
    LinearGaussianPolicy,
    lqr_true_density_ratio,
    make_lqr_behaviour,
    make_lqr_expert,
    make_lqr_optimal_policy,
)
from torchrl_wbrm.policies.mountain_car import (
    MountainCarHeuristic,
    make_mountain_car_env,
    make_mountain_car_expert,
    make_mountain_car_random_policy,
)

__all__ = [
    "LinearGaussianPolicy",
    "lqr_true_density_ratio",
    "make_lqr_behaviour",
    "make_lqr_expert",
    "make_lqr_optimal_policy",
    "MountainCarHeuristic",
    "make_mountain_car_env",
    "make_mountain_car_expert",
    "make_mountain_car_random_policy",
]
