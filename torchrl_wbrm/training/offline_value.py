r"""The delivered policy's value from the run's data alone (``eval.offline_value``): FQE of the actor on D, without
the environment, beside the online figure in ``results.json``.

The quantity is the online evaluation's own (the evaluator's
:meth:`~torchrl_wbrm.tasks.Task.return_quantity`): the γ-discounted return of an episode of at most H
steps, from D's initial states with the policy acting deterministically. On LQR that is the discounted return (its γ, over its horizon of H steps); on Minari and
MountainCar the undiscounted return over the env's episode limit. D here is the trainer's behaviour data, its
training episodes (the held-out ones are not used); the estimate averages over their initial states, while the
online evaluation starts from the env's start law, so the two agree only where D's initial states follow it.

:func:`offline_value_figures` fits FQE once unweighted and, where stage 2 read ŵ, once more weighted by the weights
stage 2 used (ŵ shaped by ``ratio.*``, stored as ``"density_ratio"``):

- ``final`` figures: ``offline_value`` with ``offline_value_ci`` (the half-width of the 95% percentile-bootstrap
  interval over D's episodes, as every ``*_ci``) and ``offline_value_low``/``offline_value_high`` (its ends), and the
  same under ``offline_value_weighted``;
- the ``offline_value`` record: the quantity in words, the episodes averaged, the FQE steps and
  ``uses_environment: false``.

``recipes/offline_value.py`` makes the same estimate for a finished run directory: its checkpoint read with
``torch.load(weights_only=True)``, the run's config from it, D rebuilt as the run built it.
"""
from __future__ import annotations

import copy

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule

from torchrl_wbrm.keys import DENSITY_RATIO, EPISODE
from torchrl_wbrm.ope.offline_value import OfflineValue, estimate_offline_value

__all__ = ["offline_value_figures"]


def _figures(prefix: str, est: OfflineValue) -> dict:
    return {prefix: est.value, f"{prefix}_ci": (est.high - est.low) / 2, f"{prefix}_low": est.low,
            f"{prefix}_high": est.high}


def offline_value_figures(
    actor: TensorDictModule,
    data: TensorDictBase,
    quantity: tuple[float, int] | None,
    *,
    weights: torch.Tensor | None = None,
    steps: int = 1000,
    seed: int = 0,
) -> tuple[dict, dict]:
    """``(final figures, record)`` of the FQE estimates of ``actor``'s value on ``data`` (D's transitions with
    ``"step_count"`` or ``"episode"``). ``quantity``: the evaluator's ``(γ, H)``; ``None`` (an evaluator that does
    not say which return it reports) gives no figure and a record saying why. ``weights``: the ``[N, 1]`` weights
    stage 2 gave D's rows, for the weighted estimate (``None``: ŵ ≡ 1, no second estimate). ``actor`` is copied to
    the CPU (the run's own is left as it is) and acts deterministically."""
    if quantity is None:
        return {}, {"skipped": "the evaluator does not state which return it reports", "uses_environment": False}
    gamma, horizon = quantity
    policy = copy.deepcopy(actor).to("cpu").eval()
    rows = data.select("observation", "action", "step_count", EPISODE, "next", strict=False).to("cpu")
    unweighted = estimate_offline_value(policy, rows, gamma=gamma, horizon=horizon, steps=steps, seed=seed)
    final = _figures("offline_value", unweighted)
    if weights is not None:
        rows = rows.clone(False).set(DENSITY_RATIO, weights.reshape(rows.shape[0], 1).to(rows["observation"].dtype))
        weighted = estimate_offline_value(policy, rows, gamma=gamma, horizon=horizon, steps=steps, seed=seed,
                                          weight_key=DENSITY_RATIO)
        final.update(_figures("offline_value_weighted", weighted))
    record = {"quantity": unweighted.quantity, "episodes": unweighted.episodes, "steps": steps,
              "weighted": weights is not None, "uses_environment": False}
    return final, record
