"""Stage 1's hand-over to stage 2 in one call: :meth:`Weighting.over` computes ŵ over a dataset (the fitted
network's, the exact ratio, or 1), shapes it and stores it in the rows, and returns with it the fitter's verdict, the
rows of the dataset's expert-like episodes and the figures recorded with the weights.
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

__all__ = ["SOURCES", "Weighting", "WeightsOver", "expert_like_figures"]

#: where ŵ comes from: the fitted network, the exact ratio (where the task knows it), or nowhere (ŵ ≡ 1)
SOURCES = ("learned", "exact", "none")


@dataclass
class WeightsOver:
    """What :meth:`Weighting.over` hands to stage 2: the ``data`` given, with the ``weights`` stored ([N, 1], shaped,
    self-normalised; ``"expert_like"`` marked where asked), ŵ before any shaping (``raw``), the fitter's ``verdict``
    on it (:meth:`~torchrl_wbrm.ratio.DensityRatioFitter.verdict`; ``None`` unless learned), the ``expert_like`` row
    mask (:func:`expert_like_figures`, where asked) and the ``figures`` of the stored weights
    (:func:`~torchrl_wbrm.evaluation.ratio_error`) and of the expert-like episodes."""

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


@dataclass
class Weighting:
    """Where a run's ŵ comes from and how it is shaped; :meth:`over` is stage 1's whole hand-over to stage 2.

    Attributes:
        source: ``"learned"`` (``network``'s ŵ, judged by ``fitter``), ``"exact"`` (``true_ratio``, relative with
            ``relative_beta``: :func:`~torchrl_wbrm.objectives.functional.relative_density_ratio`) or ``"none"``
            (ŵ ≡ 1, stored unshaped).
        network: the fitted density-ratio network (``source="learned"``).
        true_ratio: the exact ratio, a module writing ``"density_ratio"`` (``source="exact"``).
        fitter: the :class:`~torchrl_wbrm.ratio.DensityRatioFitter` whose verdict on the raw ŵ is returned.
        aggregate: ``"episode"``: each row gets its episode's weight (:func:`~torchrl_wbrm.ratio.episode_weights`).
        temper, clip, mix, self_normalise: the shaping (:func:`~torchrl_wbrm.ratio.store_density_ratio`).
        device: where the network runs.
    """

    source: str = "none"
    network: Callable | None = None
    true_ratio: Callable | None = None
    fitter: object | None = None
    relative_beta: float = 0.0
    aggregate: str = "transition"
    temper: float = 1.0
    clip: float | None = None
    mix: float = 0.0
    self_normalise: bool = True
    device: object | None = None

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise ValueError(f"Weighting: source must be one of {SOURCES}, got {self.source!r}.")

    @torch.no_grad()
    def raw(self, data: TensorDictBase) -> torch.Tensor:
        """ŵ over the rows of ``data`` before any shaping, ``[N, 1]``: the network's, the exact ratio or 1."""
        if self.source == "learned":
            return compute_density_ratio(self.network, data, chunk_size=8192, device=self.device)
        if self.source == "exact":
            raw = self.true_ratio(data.select("observation", "action"))[DENSITY_RATIO]
            return relative_density_ratio(raw, self.relative_beta) if self.relative_beta else raw
        return torch.ones(data.shape[0], 1)

    @torch.no_grad()
    def over(self, data: TensorDictBase, *, expert_like: bool = False, mark_expert_like: bool = False,
             true_expert_episodes=None, key: str = DENSITY_RATIO) -> WeightsOver:
        """ŵ over the rows of ``data`` (``"observation"``, ``"action"``; ``"episode"`` for ``aggregate="episode"`` and
        the expert-like episodes), shaped and stored there under ``key`` (``data`` is changed in place), with the
        fitter's verdict, the figures and, with ``expert_like``, the rows of the expert-like episodes
        (:func:`expert_like_figures`; ``mark_expert_like`` also marks them in ``data`` under ``"expert_like"``;
        ``true_expert_episodes``: the ids of the data's true expert episodes, for their figures).

        Raises:
            NonFiniteWeightsError: a weight is not finite (raised by :func:`~torchrl_wbrm.ratio.store_density_ratio`).
        """
        raw = self.raw(data)
        verdict = self.fitter.verdict(raw) if self.source == "learned" and self.fitter is not None else None
        rows, figures = None, {}
        if expert_like or mark_expert_like:
            rows, figures = expert_like_figures(raw, data[EPISODE], true_expert_episodes)
            if mark_expert_like:
                data.set(EXPERT_LIKE, rows.reshape(data.shape))
        w = raw
        if self.aggregate == "episode" and self.source != "none":
            w = episode_weights(w, data[EPISODE])
        stored = store_density_ratio(data, w, key=key, temper=self.temper, clip=self.clip, mix=self.mix,
                                     self_normalise=self.self_normalise and self.source != "none", keepdim=True,
                                     dtype=data["observation"].dtype)
        return WeightsOver(data=data, weights=stored, raw=raw, verdict=verdict, expert_like=rows,
                           figures={**ratio_error(stored), **figures})
