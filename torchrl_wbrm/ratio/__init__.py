"""Stage 1 of WBRM as a library: fit ŵ ≈ dP^e/dP^b, compute it over a dataset, shape it and store it.

Layer: above ``objectives`` and ``evaluation``, below ``training`` (which drives these pieces from its own loop).

- :func:`fit_density_ratio` / :class:`DensityRatioFitter`: the robust (Basu) density-ratio loss on behaviour and
  expert state-actions (TensorDicts or replay buffers), a held-out split, early stopping on the held-out loss;
  returns the best network and its diagnostics (:class:`DensityRatioFit`).
- :func:`compute_density_ratio`: ŵ over every row of a dataset, in chunks.
- :func:`store_density_ratio`: shape (:func:`shape_weights`: temper, clip, mix, self-normalise) and store it in a
  TensorDict or a replay buffer's storage under ``"density_ratio"`` (for ``WeightedBellmanLoss``, and for any
  TorchRL loss wrapped in ``WeightedLoss``) or ``"priority_weight"`` (read natively only by the TorchRL losses of
  ``NATIVE_PRIORITY_WEIGHT_LOSSES``); in a replay buffer the weights follow their rows
  (:class:`StoredWeightsFollowRows`). :func:`episode_weights` first gives each row its episode's weight, the
  geometric mean of ŵ over the episode (``ratio.aggregate=episode``); :func:`expert_like_episodes` selects the
  episodes whose self-normalised geometric mean is above 1 (``q.expert_bc_from_d``), the score
  :func:`expert_like_scores` gives each row.
- :meth:`Weighting.over`: stage 1's hand-over to stage 2 in one call: ŵ over a dataset (fitted, exact or 1), shaped
  and stored, with the fitter's verdict, the expert-like rows and the figures recorded with the weights.
"""
from torchrl_wbrm.ratio.fitting import (
    CategoricalToOneHot,
    DensityRatioFit,
    DensityRatioFitter,
    as_tensordict,
    fit_density_ratio,
    holdout_split,
)
from torchrl_wbrm.ratio.storing import (
    MissingWeightsError,
    NonFiniteWeightsError,
    StoredWeightsFollowRows,
    compute_density_ratio,
    store_density_ratio,
)
from torchrl_wbrm.ratio.weighting import Weighting, WeightsOver, expert_like_figures
from torchrl_wbrm.ratio.weights import episode_weights, expert_like_episodes, expert_like_scores, shape_weights

__all__ = [
    "CategoricalToOneHot",
    "DensityRatioFit",
    "DensityRatioFitter",
    "MissingWeightsError",
    "NonFiniteWeightsError",
    "StoredWeightsFollowRows",
    "Weighting",
    "WeightsOver",
    "as_tensordict",
    "compute_density_ratio",
    "episode_weights",
    "expert_like_episodes",
    "expert_like_figures",
    "expert_like_scores",
    "fit_density_ratio",
    "holdout_split",
    "shape_weights",
    "store_density_ratio",
]
