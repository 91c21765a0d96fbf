"""Stage 1's hand-over to stage 2 in one call: :func:`weights_over` computes ŵ over a dataset (the fitted network's,
the exact ratio, or 1), shapes it and stores it in the rows, and returns with it the fitter's verdict, the rows of
the dataset's expert-like episodes and the figures recorded with the weights.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import torch
from tensordict import TensorDictBase

from torchrl_wbrm.keys import DENSITY_RATIO, EPISODE, EXPERT_LIKE
from torchrl_wbrm.evaluation import ratio_error
from torchrl_wbrm.objectives.functional import relative_density_ratio
from torchrl_wbrm.ratio.storing import compute_density_ratio, store_density_ratio
from torchrl_wbrm.ratio.weights import episode_weights, expert_like_scores

__all__ = ["SOURCES", "WeightsOver", "expert_like_figures", "raw_density_ratio", "weights_over"]

#: where ŵ comes from: the fitted network, the exact ratio (where the task knows it), or nowhere (ŵ ≡ 1)
SOURCES = ("learned", "exact", "none")


@dataclass
class WeightsOver:
    """What :func:`weights_over` hands to stage 2.

    Attributes:
        data: the rows given, ŵ stored under ``key`` (``[N, 1]``, in the observations' dtype), and, with
            ``mark_expert_like``, the expert-like rows marked under ``"expert_like"``.
        weights: the stored weights (``[N, 1]``): shaped, self-normalised.
        raw: ŵ before any shaping (``[N, 1]``).
        verdict: the fitter's verdict on ``raw`` (:meth:`~torchrl_wbrm.ratio.DensityRatioFitter.verdict`) for a
            learned ŵ, else ``None``.
        expert_like: the row mask of the expert-like episodes (:func:`expert_like_figures`), where asked for.
        figures: the stored weights' figures (:func:`~torchrl_wbrm.evaluation.ratio_error`) and the expert-like
            episodes' (:func:`expert_like_figures`).
    """

    data: TensorDictBase
    weights: torch.Tensor
    raw: torch.Tensor
    verdict: dict | None = None
    expert_like: torch.Tensor | None = None
    figures: dict = field(default_factory=dict)


def expert_like_figures(raw: torch.Tensor, episode: torch.Tensor,
                        true_expert_episodes=None) -> tuple[torch.Tensor, dict]:
    """The rows of the expert-like episodes (:func:`~torchrl_wbrm.ratio.expert_like_episodes` of the raw ``ŵ``) and
    their figures: how many episodes and rows they hold, and, where the data name their true expert episodes
    (``true_expert_episodes``), how many of them are among those, how many of those the rows hold, and how many of
    them score above every other episode (``separable_true_episodes``: the most that any threshold on the episode
    score could select with no other episode among them)."""
    episode = episode.reshape(-1)
    score = expert_like_scores(raw, episode)
    rows = score > 1  # expert_like_episodes
    episodes = episode[rows].unique()
    figures = {"expert_like_episodes": int(episodes.numel()), "expert_like_rows": int(rows.sum())}
    if true_expert_episodes is not None:
        true_ids = torch.as_tensor(list(true_expert_episodes), dtype=torch.int64)
        figures["expert_like_true_episodes"] = int(torch.isin(episodes, true_ids).sum())
        true_rows = torch.isin(episode, true_ids)
        figures["true_expert_episodes"] = int(episode[true_rows].unique().numel())
        best_other = score[~true_rows].max() if bool((~true_rows).any()) else -math.inf
        figures["separable_true_episodes"] = int(episode[true_rows & (score > best_other)].unique().numel())
    return rows, figures


@torch.no_grad()
def raw_density_ratio(data: TensorDictBase, *, source: str, network=None, true_ratio: Callable | None = None,
                      relative_beta: float = 0.0, device=None) -> torch.Tensor:
    """ŵ over the rows of ``data`` before any shaping, ``[N, 1]``: ``network``'s (``source="learned"``), the exact
    ratio (``"exact"``, relative with ``relative_beta``) or 1 (``"none"``); see :func:`weights_over`."""
    if source not in SOURCES:
        raise ValueError(f"weights_over: source must be one of {SOURCES}, got {source!r}.")
    if source == "learned":
        return compute_density_ratio(network, data, chunk_size=8192, device=device)
    if source == "exact":
        raw = true_ratio(data.select("observation", "action"))[DENSITY_RATIO]
        return relative_density_ratio(raw, relative_beta) if relative_beta else raw
    return torch.ones(data.shape[0], 1)


@torch.no_grad()
def weights_over(data: TensorDictBase, *, source: str, network=None, true_ratio: Callable | None = None,
                 fitter=None, relative_beta: float = 0.0, aggregate: str = "transition", temper: float = 1.0,
                 clip: float | None = None, mix: float = 0.0, self_normalise: bool = True,
                 expert_like: bool = False, mark_expert_like: bool = False, true_expert_episodes=None,
                 key: str = DENSITY_RATIO, device=None) -> WeightsOver:
    """ŵ over the rows of ``data``, shaped and stored there; stage 1's whole hand-over to stage 2.

    Args:
        data: the rows (``"observation"``, ``"action"``; ``"episode"`` for ``aggregate="episode"`` and the
            expert-like episodes). Changed in place: the weights are stored in it.

    Keyword Args:
        source: ``"learned"`` (``network``'s ŵ, judged by ``fitter``), ``"exact"`` (``true_ratio``, relative with
            ``relative_beta``: :func:`~torchrl_wbrm.objectives.functional.relative_density_ratio`) or ``"none"``
            (ŵ ≡ 1, stored unshaped).
        network: the fitted density-ratio network (``source="learned"``).
        true_ratio: the exact ratio, a module writing ``"density_ratio"`` (``source="exact"``).
        fitter: the :class:`~torchrl_wbrm.ratio.DensityRatioFitter` whose verdict on the raw ŵ is returned.
        aggregate: ``"episode"``: each row gets its episode's weight (:func:`~torchrl_wbrm.ratio.episode_weights`).
        temper, clip, mix, self_normalise: the shaping (:func:`~torchrl_wbrm.ratio.store_density_ratio`).
        expert_like: find the rows of the expert-like episodes (:func:`expert_like_figures`);
            ``mark_expert_like`` also marks them in ``data`` under ``"expert_like"``.
        true_expert_episodes: the ids of the data's true expert episodes, for the expert-like figures.
        key: the entry the weights are stored under.
        device: where the network runs.

    Raises:
        NonFiniteWeightsError: a weight is not finite (raised by :func:`~torchrl_wbrm.ratio.store_density_ratio`).
    """
    raw = raw_density_ratio(data, source=source, network=network, true_ratio=true_ratio,
                            relative_beta=relative_beta, device=device)
    verdict = fitter.verdict(raw) if source == "learned" and fitter is not None else None
    rows, figures = None, {}
    if expert_like or mark_expert_like:
        rows, figures = expert_like_figures(raw, data[EPISODE], true_expert_episodes)
        if mark_expert_like:
            data.set(EXPERT_LIKE, rows.reshape(data.shape))
    w = raw
    if aggregate == "episode" and source != "none":
        w = episode_weights(w, data[EPISODE])
    stored = store_density_ratio(data, w, key=key, temper=temper, clip=clip, mix=mix,
                                 self_normalise=self_normalise and source != "none", keepdim=True,
                                 dtype=data["observation"].dtype)
    return WeightsOver(data=data, weights=stored, raw=raw, verdict=verdict, expert_like=rows,
                       figures={**ratio_error(stored), **figures})
