"""Environments: the batched LQR system of Section 5.1 with its exact solution, and its transforms; the batched,
torch-native MountainCarContinuous-v0 of Section 5.2."""
from torchrl_wbrm.envs.lqr import (
    PAPER_EXPERIMENTS,
    REWARD_CAP_87_84,
    LinearGaussianDensityRatio,
    LQRConfig,
    LQREnv,
)
from torchrl_wbrm.envs.mountain_car import MountainCarContinuousEnv
from torchrl_wbrm.envs.transforms import make_lqr_env

__all__ = [
    "LQRConfig",
    "LQREnv",
    "LinearGaussianDensityRatio",
    "MountainCarContinuousEnv",
    "PAPER_EXPERIMENTS",
    "REWARD_CAP_87_84",
    "make_lqr_env",
]
