"""Shaping of the stored per-sample weights ŵ over D (applied once, after stage 1)."""
from __future__ import annotations

import torch

__all__ = ["episode_weights", "expert_like_episodes", "expert_like_scores", "shape_weights"]


def episode_weights(w: torch.Tensor, episode: torch.Tensor) -> torch.Tensor:
    """Each row's weight replaced by its episode's: the geometric mean of ŵ over the episode's rows,
    ``exp(mean_{t in episode} log ŵ_t)``, the same for every row of one episode (``ratio.aggregate=episode``).

    A ratio fitted on a few expert episodes is large only on the states those episodes visited; an expert episode
    hidden in the behaviour data visits them most of the time, a random one rarely, so the mean of ``log ŵ`` over a
    whole episode ranks episodes by how expert-like they are, and its exponential carries that rank to every row,
    the rows the few demonstrations never reached included. A zero weight in an episode makes its weight 0.

    Args:
        w: the weights, ``[N]`` or ``[N, 1]``, finite and non-negative.
        episode: the rows' episode ids, ``[N]`` (or ``[N, 1]``), any integer labels; rows of one episode need not be
            contiguous.

    Returns:
        The episode weights, with ``w``'s shape, dtype and device (computed in float64).

    Examples:
        >>> import torch
        >>> w = torch.tensor([[1.0], [9.0], [2.0], [0.5], [8.0]])
        >>> episode_weights(w, torch.tensor([0, 0, 7, 7, 7])).reshape(-1)  # sqrt(1·9); cbrt(2·0.5·8)
        tensor([3., 3., 2., 2., 2.])
    """
    if w.shape[0] != episode.shape[0] or episode.reshape(episode.shape[0], -1).shape[1] != 1:
        raise ValueError(f"episode_weights needs one episode id per row of w: w has shape {tuple(w.shape)}, the "
                         f"episode ids {tuple(episode.shape)}.")
    if w.reshape(w.shape[0], -1).shape[1] != 1:
        raise ValueError(f"episode_weights needs one weight per row ([N] or [N, 1]), got shape {tuple(w.shape)}.")
    if not torch.isfinite(w).all() or (w < 0).any():
        raise ValueError("Weights must be finite and non-negative before they are aggregated by episode.")
    if w.numel() == 0:
        return w.clone()
    _, index = torch.unique(episode.reshape(-1).to(w.device), return_inverse=True)
    log_w = w.reshape(-1).double().log()  # log 0 = -inf: the episode's weight is then 0
    count = torch.zeros(int(index.max()) + 1, dtype=torch.float64, device=w.device)
    count.index_add_(0, index, torch.ones_like(log_w))
    total = torch.zeros_like(count).index_add_(0, index, log_w)
    return (total / count).exp()[index].reshape(w.shape).to(w.dtype)


def expert_like_episodes(w: torch.Tensor, episode: torch.Tensor) -> torch.Tensor:
    """The rows of the episodes more likely under the expert's state-action distribution than under the data's:
    those whose episode's mean of ``log(ŵ / mean ŵ)`` is above 0 (the geometric mean of the self-normalised ratio
    above 1, :func:`episode_weights`). ``Σ_t log ŵ(x_t, a_t)`` is the log-likelihood ratio of the episode's
    state-actions, d^e against d^D, each step taken alone: the episodes it selects are those a likelihood-ratio test
    at even odds calls the expert's. No threshold to set: ŵ ≡ 1 selects no episode.

    Args:
        w: the ratio over the data's rows, ``[N]`` or ``[N, 1]``, finite and non-negative (not all 0).
        episode: the rows' episode ids, ``[N]`` (or ``[N, 1]``).

    Returns:
        A boolean mask ``[N]``: the rows of the selected episodes.

    Examples:
        >>> import torch
        >>> w = torch.tensor([3.0, 3.0, 0.1, 0.2, 0.1, 1.0])
        >>> expert_like_episodes(w, torch.tensor([0, 0, 1, 1, 1, 2])).tolist()
        [True, True, False, False, False, False]
        >>> expert_like_episodes(torch.ones(4), torch.tensor([0, 0, 1, 1])).any().item()
        False
    """
    return expert_like_scores(w, episode) > 1


def expert_like_scores(w: torch.Tensor, episode: torch.Tensor) -> torch.Tensor:
    """Each row's episode score, the one :func:`expert_like_episodes` holds against 1: the geometric mean over the
    row's episode of ``ŵ / mean ŵ`` (:func:`episode_weights` of the self-normalised ratio), ``[N]`` in float64.

    Examples:
        >>> import torch
        >>> expert_like_scores(torch.tensor([4.0, 1.0, 1.0]), torch.tensor([0, 0, 1]))  # mean 2: sqrt(2 · 0.5), 0.5
        tensor([1.0000, 1.0000, 0.5000], dtype=torch.float64)
    """
    flat = w.reshape(-1).double()
    mean = flat.mean() if flat.numel() else flat.new_ones(())
    if not mean > 0:
        raise ValueError("expert_like_episodes needs weights with a positive mean over the data, got "
                         f"{float(mean)!r}.")
    return episode_weights(flat / mean, episode.reshape(-1))


def shape_weights(
    w: torch.Tensor,
    *,
    temper: float = 1.0,
    clip: float | None = None,
    mix: float = 0.0,
    self_normalise: bool = True,
) -> torch.Tensor:
    """``w -> (1 - mix) * v / mean(v) + mix`` with ``v = min(w^temper, clip)``, then divided by its mean over D if
    ``self_normalise``.

    - ``temper`` (λ in ŵ^λ, 0 < λ ≤ 1) flattens a peaked ratio while keeping its order (the recipe stores ŵ^0.25:
      of the tempers tried by ``recipes/weighting_study.py`` it gave the lowest held-out Bellman residual);
    - ``clip`` caps single samples' influence;
    - ``mix`` puts a floor ``mix`` under every sample's weight;
    - ``self_normalise`` makes the weights average 1 over D, so the loss's scale (and learning rate) does not
      depend on how well ŵ's behaviour mean came out.

    All are off by default except self-normalisation.

    Examples:
        >>> import torch
        >>> w = torch.tensor([0.0, 1.0, 4.0, 16.0])
        >>> shape_weights(w, temper=0.5)  # sqrt, then mean 1
        tensor([0.0000, 0.5714, 1.1429, 2.2857])
        >>> shape_weights(w, clip=2.0, self_normalise=False)
        tensor([0., 1., 2., 2.])
        >>> shape_weights(w, mix=0.5).min()  # a floor under every weight
        tensor(0.5000)
    """
    if not torch.isfinite(w).all() or (w < 0).any():
        raise ValueError("Weights must be finite and non-negative before shaping.")
    if not 0.0 < temper <= 1.0:
        raise ValueError(f"temper must lie in (0, 1], got {temper}.")
    if not 0.0 <= mix <= 1.0:
        raise ValueError(f"mix must lie in [0, 1], got {mix}.")
    out = w.double()
    if temper != 1.0:
        out = out.pow(temper)
    if clip is not None:
        if not clip > 0:
            raise ValueError(f"clip must be > 0, got {clip}.")
        out = out.clamp_max(clip)
    if mix:
        out = (1.0 - mix) * out / out.mean() + mix
    if self_normalise:
        mean = out.mean()
        if not mean > 0:
            raise ValueError("Cannot self-normalise weights whose mean is 0.")
        out = out / mean
    return out.to(w.dtype)
