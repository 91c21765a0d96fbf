"""Fixed feature maps of (x, a): the linear-span classes of MABO's adversary (``adversary="linear"``)."""
from __future__ import annotations

import torch
from torch import nn

__all__ = ["PolynomialFeatures"]


class PolynomialFeatures(nn.Module):
    """All monomials of ``z = (x, a)`` up to ``degree`` (1 or 2): ``(1, z)`` or ``(1, z, z_i z_j for i ≤ j)``.

    With ``d = dim(z)`` there are ``1 + d`` features for degree 1 and ``1 + d + d(d + 1)/2`` for degree 2 (LQR exp1,
    d = 4: 15). A degree-2 span contains the quadratic Q* of an LQR and every Gaussian-ratio log-density; it has no
    parameters and is never trained.

    Examples:
        >>> import torch
        >>> PolynomialFeatures(2)(torch.tensor([[2.0]]), torch.tensor([[3.0]]))  # 1, x, a, x², xa, a²
        tensor([[1., 2., 3., 4., 6., 9.]])
    """

    def __init__(self, degree: int = 2) -> None:
        super().__init__()
        if degree not in (1, 2):
            raise ValueError(f"degree must be 1 or 2, got {degree!r}.")
        self.degree = degree

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        if observation.shape[:-1] != action.shape[:-1]:
            raise ValueError(
                f"observation {tuple(observation.shape)} and action {tuple(action.shape)} must share batch dimensions."
            )
        z = torch.cat([observation, action], -1)
        parts = [torch.ones_like(z[..., :1]), z]
        if self.degree == 2:
            i, j = torch.triu_indices(z.shape[-1], z.shape[-1], device=z.device)
            parts.append(z[..., i] * z[..., j])
        return torch.cat(parts, -1)

    def num_features(self, dim: int) -> int:
        """The number of features for ``dim = dim(x) + dim(a)``."""
        return 1 + dim + (dim * (dim + 1) // 2 if self.degree == 2 else 0)

    def extra_repr(self) -> str:
        return f"degree={self.degree}"
