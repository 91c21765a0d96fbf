r"""Maximisers: ``max_{a'} Q(x', a')`` for the Bellman target ``T*Q(x, a) = r + γ max_{a'} Q(x', a')`` (Section 3).

A maximiser's :meth:`ActionMaximiser.maximise` is the one implementation: it is called as
``maximiser.maximise(q, observations, batch_shape, action_key=..., actor_action=...)`` with ``q(inputs,
batch_shape)`` a function that evaluates Q on a mapping of input tensors (the loss's
:class:`~torchrl_wbrm.objectives._fast.NetworkCall`, with the parameters, online or target, and the gradient mode the
loss chose), and returns the maximum over actions, of shape ``batch_shape``. Calling the maximiser as a module,
``maximiser(q_network, tensordict, ...)``, runs the same method on a TensorDict module.

- :class:`GreedyDiscreteMaximiser`: discrete actions, ``max_a Q(x, a)`` over a Q head writing ``"action_value"``
  (as TorchRL's DQNLoss).
- :class:`ActorMaximiser`: continuous actions, ``max_a Q(x, a) ≈ Q(x, μ(x))`` (DDPG / TD3+BC).
- :class:`SampledActionMaximiser`: continuous actions, the best of ``num_samples`` actions drawn uniformly in the
  action spec's box, plus ``μ(x)`` when an actor is given. Needs no actor; an underestimate of the max that tightens
  as ``num_samples`` grows.
"""
from __future__ import annotations

import abc
from typing import Callable, Mapping

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Bounded

__all__ = [
    "ActionMaximiser",
    "ActorMaximiser",
    "GreedyDiscreteMaximiser",
    "SampledActionMaximiser",
    "max_over_candidates",
    "max_q_over_candidates",
    "uniform_actions",
]


def uniform_actions(low: torch.Tensor, high: torch.Tensor, num_samples: int, batch_shape: torch.Size) -> torch.Tensor:
    """``num_samples`` actions per batch element, uniform in the box ``[low, high]``: shape ``[K, *B, *A]``."""
    shape = (num_samples, *batch_shape, *low.shape)
    return low + (high - low) * torch.rand(shape, device=low.device, dtype=low.dtype)


#: ``q(inputs, batch_shape) -> Q``: Q's raw output on a mapping of input tensors with leading shape ``batch_shape``.
QFunction = Callable[[Mapping[NestedKey, torch.Tensor], torch.Size], torch.Tensor]


def max_over_candidates(
    q: QFunction,
    observations: Mapping[NestedKey, torch.Tensor],
    candidates: torch.Tensor,
    batch_shape: torch.Size,
    *,
    action_key: NestedKey = "action",
) -> torch.Tensor:
    """``max_k Q(x, a_k)`` over candidate actions ``candidates`` of shape ``[K, *B, *A]`` (``B = batch_shape``);
    returns shape ``[*B]``.

    The K candidates are evaluated in one batched call of ``q`` on ``[K, *B]`` (the observations expanded, no
    Python loop over candidates or batch). The gradient, if any, flows through the chosen candidate's Q value.
    """
    k = candidates.shape[0]
    inputs = {key: value.expand(k, *value.shape) for key, value in observations.items()}
    inputs[action_key] = candidates
    return q(inputs, torch.Size([k, *batch_shape])).squeeze(-1).max(0).values


def _td_function(q_network: TensorDictModuleBase, value_key: NestedKey, device) -> QFunction:
    """A :data:`QFunction` of a TensorDict module: the inputs in a new TensorDict, ``value_key`` read."""

    def q(inputs, batch_shape):
        return q_network(TensorDict(dict(inputs), batch_size=batch_shape, device=device)).get(value_key)

    return q


def max_q_over_candidates(
    q_network: TensorDictModuleBase,
    tensordict: TensorDictBase,
    candidates: torch.Tensor,
    *,
    action_key: NestedKey = "action",
    value_key: NestedKey = "state_action_value",
) -> torch.Tensor:
    """:func:`max_over_candidates` for a TensorDict module ``q_network`` reading ``tensordict``'s entries."""
    observations = {key: tensordict.get(key) for key in tensordict.keys(True, True) if key != action_key}
    q = _td_function(q_network, value_key, tensordict.device)
    return max_over_candidates(q, observations, candidates, tensordict.batch_size, action_key=action_key)


class ActionMaximiser(nn.Module, abc.ABC):
    """Base class: :meth:`maximise` on tensors; called as a module on a TensorDict module and a TensorDict."""

    needs_actor: bool = False
    #: Whether :meth:`maximise` draws random numbers (a loss using it then has ``vmap_randomness == "different"``).
    draws_random: bool = False

    @abc.abstractmethod
    def maximise(
        self,
        q: QFunction,
        observations: Mapping[NestedKey, torch.Tensor],
        batch_shape: torch.Size,
        *,
        action_key: NestedKey = "action",
        actor_action: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """``max_a Q(x, a)`` of shape ``batch_shape``, with ``q`` a :data:`QFunction` and ``observations`` Q's inputs
        other than the action."""

    def forward(
        self,
        q_network: TensorDictModuleBase,
        tensordict: TensorDictBase,
        *,
        action_key: NestedKey = "action",
        value_key: NestedKey = "state_action_value",
        actor_action: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """:meth:`maximise` with Q the TensorDict module ``q_network`` (its output ``value_key``) on the entries of
        ``tensordict``."""
        observations = {key: tensordict.get(key) for key in tensordict.keys(True, True) if key != action_key}
        return self.maximise(_td_function(q_network, value_key, tensordict.device), observations,
                             tensordict.batch_size, action_key=action_key, actor_action=actor_action)


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

    def maximise(self, q, observations, batch_shape, *, action_key="action", actor_action=None):
        return q(observations, batch_shape).max(-1).values

    def forward(self, q_network, tensordict, *, action_key="action", value_key="action_value", actor_action=None):
        return super().forward(q_network, tensordict, action_key=action_key, value_key=value_key,
                               actor_action=actor_action)


class ActorMaximiser(ActionMaximiser):
    """``max_a Q(x, a) ≈ Q(x, μ(x))`` with ``actor_action = μ(x)`` computed by the caller (the loss)."""

    needs_actor = True

    def maximise(self, q, observations, batch_shape, *, action_key="action", actor_action=None):
        if actor_action is None:
            raise ValueError("ActorMaximiser needs actor_action = μ(x); build the loss with an actor_network.")
        # one candidate: Q(x, μ(x)) itself, evaluated on [*B] (the same matrix products on the same rows as a
        # [1, *B] evaluation, and the max of one value is that value)
        return q({**observations, action_key: actor_action}, batch_shape).squeeze(-1)


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

    draws_random = True

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

    def maximise(self, q, observations, batch_shape, *, action_key="action", actor_action=None):
        candidates = uniform_actions(self.low, self.high, self.num_samples, batch_shape)
        if actor_action is not None:
            candidates = torch.cat([candidates, actor_action.unsqueeze(0)], 0)
        return max_over_candidates(q, observations, candidates, batch_shape, action_key=action_key)

    def extra_repr(self) -> str:
        return f"num_samples={self.num_samples}"
