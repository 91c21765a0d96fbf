"""Environments: the batched LQR system of Section 5.1 with its exact solution, and its transforms."""
from torchrl_wbrm.envs.lqr import (
    PAPER_EXPERIMENTS,
    REWARD_CAP_87_84,
    LinearGaussianDensityRatio,
    LQRConfig,
    LQREnv,
)
from torchrl_wbrm.envs.transforms import make_lqr_env

__all__ = ["LQRConfig", "LQREnv", "LinearGaussianDensityRatio", "PAPER_EXPERIMENTS", "REWARD_CAP_87_84", "make_lqr_env"]
