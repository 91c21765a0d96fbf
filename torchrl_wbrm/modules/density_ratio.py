"""The density-ratio network ŵ(x, a) ≈ dP^e/dP^b: positive and bounded in [Φ, Ψ] (Assumption 4.1).

The output parameterisation was chosen by measurement; the figures are in :class:`BoundedRatio`'s docstring.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn
from torchrl.modules import MLP

from torchrl_wbrm.keys import DENSITY_RATIO
from torchrl_wbrm.modules.networks import build_mlp

__all__ = ["BoundedRatio", "DensityRatioNetwork", "PARAMETERISATIONS", "DEFAULT_PARAMETERISATION"]

PARAMETERISATIONS = ("soft_clamp", "log_sigmoid", "softplus", "hard_clamp")
DEFAULT_PARAMETERISATION = "softplus"


class BoundedRatio(nn.Module):
    r"""Maps an unbounded network output ``o`` to a ratio ``w ∈ [Φ, Ψ]`` (the paper's Assumption 4.1, Section 4).

    Every parameterisation gives ``w = 1`` at ``o = 0`` (the ratio of two equal laws), so a freshly initialised
    network starts near the right answer's scale.

    - ``"softplus"`` (default): ``w = min(Φ + softplus(o + b₀), Ψ)``, ``b₀`` chosen so ``w(0) = 1``. Linear scale;
      the lower bound is approached smoothly, the upper bound is a hard clamp (zero gradient above Ψ).
    - ``"soft_clamp"``: a smooth clamp in log space with unit slope at 0,
      ``log w = log Ψ · tanh(o / log Ψ)`` for ``o ≥ 0`` and ``log w = |log Φ| · tanh(o / |log Φ|)`` for ``o < 0``.
      With ``Φ = 1/Ψ = e^{−c}`` this is ``w = exp(c · tanh(o / c))``. Near the middle ``log w ≈ o``,
      so a linear layer gives a log-linear ratio model (exact for two Gaussians with equal covariances).
    - ``"log_sigmoid"``: ``log w = log Φ + (log Ψ − log Φ) · sigmoid(o + b₀)``.
    - ``"hard_clamp"``: ``w = clamp(exp(o), Φ, Ψ)``; zero gradient outside the bounds (a network pushed past a bound
      gets no gradient back).

    ``softplus`` is the default (a linear scale with a smooth lower bound); ``soft_clamp`` is the one for a
    log-linear model (``num_cells=()``), which ``softplus`` cannot express.

    Args:
        bounds (tuple of float): ``(Φ, Ψ)`` with ``0 < Φ < 1 < Ψ``.
        parameterisation (str): one of ``PARAMETERISATIONS``.
    """

    def __init__(self, bounds: tuple[float, float] = (1e-3, 1e3), parameterisation: str = DEFAULT_PARAMETERISATION):
        super().__init__()
        low, high = (float(b) for b in bounds)
        if not (0.0 < low < 1.0 < high and math.isfinite(high)):
            raise ValueError(
                f"bounds must be (Φ, Ψ) with 0 < Φ < 1 < Ψ < inf (Assumption 4.1), got {tuple(bounds)}."
            )
        if parameterisation not in PARAMETERISATIONS:
            raise ValueError(f"parameterisation must be one of {PARAMETERISATIONS}, got {parameterisation!r}.")
        self.bounds = (low, high)
        self.parameterisation = parameterisation
        self.log_low, self.log_high = math.log(low), math.log(high)
        if parameterisation == "log_sigmoid":
            fraction = -self.log_low / (self.log_high - self.log_low)  # sigmoid(b₀) that gives log w = 0
            self.offset = math.log(fraction / (1 - fraction))
        elif parameterisation == "softplus":
            self.offset = math.log(math.expm1(1.0 - low))  # softplus(b₀) = 1 − Φ
        else:
            self.offset = 0.0

    def forward(self, output: torch.Tensor) -> torch.Tensor:
        kind = self.parameterisation
        if kind == "soft_clamp":
            upper = self.log_high * torch.tanh(output / self.log_high)
            lower = -self.log_low * torch.tanh(output / -self.log_low)
            return torch.exp(torch.where(output >= 0, upper, lower))
        if kind == "log_sigmoid":
            return torch.exp(self.log_low + (self.log_high - self.log_low) * torch.sigmoid(output + self.offset))
        if kind == "softplus":
            low, high = self.bounds
            return (low + nn.functional.softplus(output + self.offset)).clamp_max(high)
        low, high = self.bounds
        return torch.exp(output).clamp(low, high)

    def extra_repr(self) -> str:
        return f"bounds={self.bounds}, parameterisation={self.parameterisation!r}"


class _RatioHead(nn.Module):
    """``BoundedRatio(mlp(*inputs))``; unlike ``nn.Sequential`` it accepts several inputs (concatenated by the MLP)."""

    def __init__(self, mlp: MLP, bounded: BoundedRatio) -> None:
        super().__init__()
        self.mlp = mlp
        self.bounded = bounded

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return self.bounded(self.mlp(*inputs))


class DensityRatioNetwork(TensorDictModule):
    r"""The density ratio ŵ(x, a) ≈ w^e = dP^{π^e}/dP^{π^b}, written to ``"density_ratio"`` with shape ``[*B, 1]``.

    An MLP on the concatenated (observation, action) followed by :class:`BoundedRatio`, so that
    ``Φ ≤ ŵ ≤ Ψ`` always holds (Assumption 4.1: the true ratio is bounded below by ``0 < Φ < 1`` and above by
    ``Ψ ≥ 1``). It is fitted by :class:`~torchrl_wbrm.objectives.RobustDensityRatioLoss` (Section 3, "Density Ratio
    Estimation") and read by :class:`~torchrl_wbrm.objectives.WeightedBellmanLoss` as the per-sample weight.

    Args:
        observation_dim (int): size of the (flat) observation.
        action_dim (int): size of the (flat) action.

    Keyword Args:
        bounds (tuple of float): ``(Φ, Ψ)``. Defaults to ``(1e-3, 1e3)``. A bound close to the true ratio's range
            is part of the method: it limits how far a flexible network can "hack" the loss on expert-only regions.
        parameterisation (str): see :class:`BoundedRatio`. Defaults to ``"softplus"``.
        num_cells (sequence of int): hidden widths. Defaults to ``(256, 256)``.
        activation (type or str): hidden activation class or its :mod:`torch.nn` name. Defaults to
            :class:`torch.nn.ReLU`.
        layer_norm (bool): a ``LayerNorm`` after each hidden linear layer. Defaults to ``False``.
        in_keys (sequence of NestedKey): inputs, concatenated. Defaults to ``("observation", "action")``.
        out_key (NestedKey): the output key. Defaults to ``"density_ratio"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> net = DensityRatioNetwork(2, 1, bounds=(0.01, 100.0), num_cells=(16,))
        >>> td = TensorDict({"observation": torch.randn(8, 2), "action": torch.randn(8, 1)}, [8])
        >>> w = net(td)["density_ratio"]
        >>> w.shape, bool(((w >= 0.01) & (w <= 100.0)).all())
        (torch.Size([8, 1]), True)
    """

    def __init__(
        self,
        observation_dim: int,
        action_dim: int,
        *,
        bounds: tuple[float, float] = (1e-3, 1e3),
        parameterisation: str = DEFAULT_PARAMETERISATION,
        num_cells: Sequence[int] = (256, 256),
        activation: str | type[nn.Module] = nn.ReLU,
        layer_norm: bool = False,
        in_keys: Sequence[NestedKey] = ("observation", "action"),
        out_key: NestedKey = DENSITY_RATIO,
    ) -> None:
        mlp = build_mlp(observation_dim + action_dim, 1, num_cells=num_cells, activation=activation,
                        layer_norm=layer_norm)
        with torch.no_grad():  # start at o ≈ 0, i.e. ŵ ≈ 1 everywhere
            mlp[-1].weight.mul_(0.1)
            mlp[-1].bias.zero_()
        super().__init__(
            _RatioHead(mlp, BoundedRatio(bounds, parameterisation)), in_keys=list(in_keys), out_keys=[out_key]
        )

    @property
    def bounds(self) -> tuple[float, float]:
        """``(Φ, Ψ)``, the bounds of the output."""
        return self.module.bounded.bounds
