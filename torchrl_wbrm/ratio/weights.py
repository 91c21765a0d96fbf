"""Shaping of the stored per-sample weights ŵ over D (applied once, after stage 1)."""
from __future__ import annotations

import torch

__all__ = ["shape_weights"]


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
