"""Off-policy evaluation: a policy's value from logged data alone, without the environment.

Layer: above ``objectives`` (it fits :class:`~torchrl_wbrm.objectives.FQELoss`) and ``evaluation``, below ``algos``
and ``training``.

- :func:`estimate_offline_value` / :func:`fit_fqe`: FQE of a policy on D, optionally ŵ-weighted, and the mean of
  ``Q̂(x_0, π(x_0))`` over D's initial states with a 95% bootstrap interval over episodes (:class:`OfflineValue`); in
  finite-horizon mode the quantity the online evaluation reports.
- :class:`LinearQ`, :func:`least_squares_fqe`, :class:`GreedyQuadraticPolicy`: Q linear in polynomial features,
  fitted by least-squares FQE (or FQI with the greedy policy), for studies with Q classes that cannot fit Q
  everywhere.
"""
from torchrl_wbrm.ope.linear_fqe import GreedyQuadraticPolicy, LinearQ, least_squares_fqe
from torchrl_wbrm.ope.offline_value import (
    TIME_LEFT_KEY,
    OfflineValue,
    estimate_offline_value,
    fit_fqe,
    initial_rows,
    value_at,
    with_time_left,
)

__all__ = [
    "GreedyQuadraticPolicy",
    "LinearQ",
    "OfflineValue",
    "TIME_LEFT_KEY",
    "estimate_offline_value",
    "fit_fqe",
    "initial_rows",
    "least_squares_fqe",
    "value_at",
    "with_time_left",
]
