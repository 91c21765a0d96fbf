"""Evaluation against the truth: returns, paired regret, Q* error, ratio error, confidence intervals."""
from torchrl_wbrm.evaluation.metrics import (
    FiniteHorizonLQRPolicy,
    discounted_returns,
    evaluate_returns,
    lqr_paired_regret,
    q_error,
    ratio_error,
)
from torchrl_wbrm.evaluation.stats import MeanCI, bootstrap_ci, mean_ci

__all__ = [
    "FiniteHorizonLQRPolicy",
    "MeanCI",
    "bootstrap_ci",
    "discounted_returns",
    "evaluate_returns",
    "lqr_paired_regret",
    "mean_ci",
    "q_error",
    "ratio_error",
]
