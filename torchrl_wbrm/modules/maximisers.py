r"""Maximisers: ``max_{a'} Q(x', a')`` for the Bellman target ``T*Q(x, a) = r + γ max_{a'} Q(x', a')`` (Section 3).

A maximiser is called as ``maximiser(q_network, tensordict, action_key=..., value_key=..., actor_action=...)``
and returns the maximum over actions, of the tensordict's batch shape. It only *calls* ``q_network``; the loss decides
which parameters are loaded into it (online or target) and whether gradients flow.

- :class:`GreedyDiscreteMaximiser`: discrete actions, ``max_a Q(x, a)`` over a Q head writing ``"action_value"``
  (as TorchRL's DQNLoss).
- :class:`ActorMaximiser`: continuous actions, ``max_a Q(x, a) ≈ Q(x, μ(x))`` (DDPG / TD3+BC).
- :class:`SampledActionMaximiser`: continuous actions, the best of ``num_samples`` actions drawn uniformly in the
  action spec's box, plus ``μ(x)`` when an actor is given. Needs no actor; an underestimate of the max that tightens
  as ``num_samples`` grows.
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Bounded

__all__ = [
    "ActionMaximiser",
    "ActorMaximiser",
    "GreedyDiscreteMaximiser",
    "SampledActionMaximiser",
    "max_q_over_candidates",
    "uniform_actions",
]


def uniform_actions(low: torch.Tensor, high: torch.Tensor, num_samples: int, batch_shape: torch.Size) -> torch.Tensor:
    """``num_samples`` actions per batch element, uniform in the box ``[low, high]``: shape ``[K, *B, *A]``."""
    shape = (num_samples, *batch_shape, *low.shape)
    return low + (high - low) * torch.rand(shape, device=low.device, dtype=low.dtype)


def max_q_over_candidates(
    q_network: TensorDictModuleBase,
    tensordict: TensorDictBase,
    candidates: torch.Tensor,
    *,
    action_key: NestedKey = "action",
    value_key: NestedKey = "state_action_value",
) -> torch.Tensor:
    """``max_k Q(x, a_k)`` over candidate actions ``candidates`` of shape ``[K, *B, *A]``; returns shape ``[*B]``.

    The K candidates are evaluated in one batched call of ``q_network`` (no Python loop over candidates or batch).
    The gradient, if any, flows through the chosen candidate's Q value.
    """
    num_candidates = candidates.shape[0]
    expanded = tensordict.expand(num_candidates, *tensordict.batch_size).clone(False)
    expanded.set(action_key, candidates)
    values = q_network(expanded).get(value_key).squeeze(-1)  # [K, *B]
    return values.max(0).values


class ActionMaximiser(nn.Module):
    """Base class: ``forward(q_network, tensordict, *, action_key, value_key, actor_action=None) -> max_a Q``."""

    needs_actor: bool = False

    def forward(
        self,
        q_network: TensorDictModuleBase,
        tensordict: TensorDictBase,
        *,
        action_key: NestedKey = "action",
        value_key: NestedKey = "state_action_value",
        actor_action: torch.Tensor | None = None,
    ) -> torch.Tensor:
        raise NotImplementedError


class GreedyDiscreteMaximiser(ActionMaximiser):
    """``max_a Q(x, a)`` over a discrete Q head; ``value_key`` names the per-action values (``"action_value"``).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_wbrm.modules import make_discrete_q_network
        >>> q = make_discrete_q_network(2, 3, num_cells=(8,))
        >>> td = TensorDict({"observation": torch.randn(4, 2)}, [4])
        >>> GreedyDiscreteMaximiser()(q, td, value_key="action_value").shape
        torch.Size([4])
    """

    def forward(self, q_network, tensordict, *, action_key="action", value_key="action_value", actor_action=None):
        return q_network(tensordict.copy()).get(value_key).max(-1).values


class ActorMaximiser(ActionMaximiser):
    """``max_a Q(x, a) ≈ Q(x, μ(x))`` with ``actor_action = μ(x)`` computed by the caller (the loss)."""

    needs_actor = True

    def forward(self, q_network, tensordict, *, action_key="action", value_key="state_action_value", actor_action=None):
        if actor_action is None:
            raise ValueError("ActorMaximiser needs actor_action = μ(x); build the loss with an actor_network.")
        return max_q_over_candidates(
            q_network, tensordict, actor_action.unsqueeze(0), action_key=action_key, value_key=value_key
        )


class SampledActionMaximiser(ActionMaximiser):
    """The best of ``num_samples`` uniform actions in the spec's box, plus ``μ(x)`` when ``actor_action`` is given.

    Args:
        action_spec (Bounded): the action spec; its bounds must be finite.

    Keyword Args:
        num_samples (int): uniform candidates per state. Defaults to ``64``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Bounded
        >>> from torchrl_wbrm.modules import make_q_network
        >>> q = make_q_network(2, 1, initial_bias=0.0, num_cells=(8,))
        >>> maximiser = SampledActionMaximiser(Bounded(-1.0, 1.0, (1,)), num_samples=16)
        >>> maximiser(q, TensorDict({"observation": torch.randn(4, 2)}, [4])).shape
        torch.Size([4])
    """

    def __init__(self, action_spec: Bounded, *, num_samples: int = 64) -> None:
        super().__init__()
        if not isinstance(action_spec, Bounded):
            raise ValueError(f"SampledActionMaximiser needs a Bounded action spec, got {type(action_spec).__name__}.")
        low, high = action_spec.space.low, action_spec.space.high
        if not (torch.isfinite(low).all() and torch.isfinite(high).all()):
            raise ValueError(f"SampledActionMaximiser needs finite action bounds, got low={low} and high={high}.")
        if num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, got {num_samples}.")
        self.num_samples = int(num_samples)
        self.register_buffer("low", low.clone())
        self.register_buffer("high", high.clone())

    def forward(self, q_network, tensordict, *, action_key="action", value_key="state_action_value", actor_action=None):
        candidates = uniform_actions(self.low, self.high, self.num_samples, tensordict.batch_size)
        if actor_action is not None:
            candidates = torch.cat([candidates, actor_action.unsqueeze(0)], 0)
        return max_q_over_candidates(q_network, tensordict, candidates, action_key=action_key, value_key=value_key)

    def extra_repr(self) -> str:
        return f"num_samples={self.num_samples}"
