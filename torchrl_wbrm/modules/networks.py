"""Network builders: a Q network on (observation, action), a discrete Q head, a bounded deterministic actor.

All builders return ordinary TorchRL modules (:class:`~torchrl.modules.ValueOperator`,
:class:`~torchrl.modules.QValueActor`, :class:`~torchrl.modules.Actor`), so they plug into TorchRL losses, collectors
and :class:`~torchrl_wbrm.objectives.WeightedBellmanLoss` alike. The paper (Section 3) fits Q and the ratio with
ReLU networks, hence ReLU is the default activation here.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Bounded, Categorical, OneHot, TensorSpec
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torchrl.envs.utils import ExplorationType
from torchrl.modules import MLP, Actor, ProbabilisticActor, QValueActor, TanhNormal, ValueOperator

__all__ = [
    "BoundedTanh",
    "make_deterministic_actor",
    "make_discrete_q_network",
    "make_q_network",
    "make_tanh_normal_actor",
]


def _mlp(in_features: int, out_features: int, num_cells: Sequence[int], activation: type[nn.Module]) -> MLP:
    return MLP(in_features=in_features, out_features=out_features, num_cells=list(num_cells), activation_class=activation)


def _set_output_bias(mlp: MLP, initial_bias: float) -> None:
    """Start the last layer's bias at ``initial_bias``.

    Offline Q targets are of order mean(r)/(1 − γ) (about 100 on the LQR task with γ = 0.9); a network starting at 0
    spends thousands of steps moving its constant (DESIGN.md, "Measured on this machine").
    """
    last = mlp[-1]
    if not isinstance(last, nn.Linear) or last.bias is None:
        raise ValueError(f"Expected the MLP to end with a biased nn.Linear, got {type(last).__name__}.")
    with torch.no_grad():
        last.bias.fill_(float(initial_bias))


def make_q_network(
    observation_dim: int,
    action_dim: int,
    *,
    num_cells: Sequence[int] = (256, 256),
    activation: type[nn.Module] = nn.ReLU,
    initial_bias: float = 0.0,
    in_keys: Sequence[NestedKey] = ("observation", "action"),
    out_key: NestedKey = "state_action_value",
) -> ValueOperator:
    """A Q network ``Q(x, a)`` on the concatenated (observation, action), written to ``"state_action_value"``.

    Args:
        observation_dim (int): size of the (flat) observation.
        action_dim (int): size of the (flat) action.

    Keyword Args:
        num_cells (sequence of int): hidden layer widths. Defaults to ``(256, 256)``.
        activation (type): hidden activation class. Defaults to :class:`torch.nn.ReLU`.
        initial_bias (float): starting value of the output bias. Set it to ``mean(r) / (1 − γ)`` so that Q starts
            near the scale of its targets. Defaults to ``0.0``.
        in_keys (sequence of NestedKey): the observation and action keys, concatenated in this order.
        out_key (NestedKey): where Q is written. Defaults to ``"state_action_value"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> q = make_q_network(3, 2, num_cells=(16,), initial_bias=10.0)
        >>> td = TensorDict({"observation": torch.zeros(5, 3), "action": torch.zeros(5, 2)}, [5])
        >>> q(td)["state_action_value"].shape
        torch.Size([5, 1])
    """
    mlp = _mlp(observation_dim + action_dim, 1, num_cells, activation)
    _set_output_bias(mlp, initial_bias)
    return ValueOperator(mlp, in_keys=list(in_keys), out_keys=[out_key])


def make_discrete_q_network(
    observation_dim: int,
    num_actions: int,
    *,
    action_space: str = "one-hot",
    num_cells: Sequence[int] = (256, 256),
    activation: type[nn.Module] = nn.ReLU,
    initial_bias: float = 0.0,
    in_keys: Sequence[NestedKey] = ("observation",),
) -> QValueActor:
    """A discrete Q head ``x ↦ (Q(x, a))_a``: a :class:`~torchrl.modules.QValueActor` writing ``"action_value"``.

    The actor also writes the greedy ``"action"`` and its ``"chosen_action_value"``, exactly as TorchRL's DQN expects.

    Args:
        observation_dim (int): size of the (flat) observation.
        num_actions (int): number of discrete actions.

    Keyword Args:
        action_space (str): ``"one-hot"`` (default) or ``"categorical"``: how actions are encoded.
        num_cells, activation, initial_bias, in_keys: as in :func:`make_q_network`.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> q = make_discrete_q_network(4, 3, num_cells=(16,))
        >>> out = q(TensorDict({"observation": torch.randn(2, 4)}, [2]))
        >>> out["action_value"].shape, out["action"].shape
        (torch.Size([2, 3]), torch.Size([2, 3]))
    """
    if action_space == "one-hot":
        spec: TensorSpec = OneHot(num_actions)
    elif action_space == "categorical":
        spec = Categorical(num_actions)
    else:
        raise ValueError(f"action_space must be 'one-hot' or 'categorical', got {action_space!r}.")
    mlp = _mlp(observation_dim, num_actions, num_cells, activation)
    _set_output_bias(mlp, initial_bias)
    return QValueActor(mlp, in_keys=list(in_keys), spec=spec)


class BoundedTanh(nn.Module):
    """Maps an unbounded input into the box ``[low, high]``: ``low + (high − low) · (tanh(u) + 1) / 2``."""

    def __init__(self, low: torch.Tensor, high: torch.Tensor) -> None:
        super().__init__()
        low = torch.as_tensor(low, dtype=torch.get_default_dtype())
        high = torch.as_tensor(high, dtype=torch.get_default_dtype())
        if not (torch.isfinite(low).all() and torch.isfinite(high).all()):
            raise ValueError(f"BoundedTanh needs finite bounds, got low={low} and high={high}.")
        if (low >= high).any():
            raise ValueError(f"BoundedTanh needs low < high elementwise, got low={low} and high={high}.")
        self.register_buffer("low", low)
        self.register_buffer("high", high)

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        return self.low + (self.high - self.low) * (torch.tanh(u) + 1) / 2


def make_deterministic_actor(
    observation_dim: int,
    action_spec: Bounded,
    *,
    num_cells: Sequence[int] = (256, 256),
    activation: type[nn.Module] = nn.ReLU,
    in_keys: Sequence[NestedKey] = ("observation",),
    out_key: NestedKey = "action",
) -> Actor:
    """A deterministic actor ``μ(x)`` whose output lies inside the bounds of ``action_spec`` (a ``Bounded`` spec).

    The action is ``low + (high − low) · (tanh(u) + 1) / 2`` with ``u`` the MLP's output, so it never leaves the box;
    at initialisation it sits near the centre of the box.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Bounded
        >>> spec = Bounded(-2.0, 2.0, (1,))
        >>> actor = make_deterministic_actor(3, spec, num_cells=(16,))
        >>> action = actor(TensorDict({"observation": 100 * torch.randn(4, 3)}, [4]))["action"]
        >>> bool((action.abs() <= 2).all())
        True
    """
    if not isinstance(action_spec, Bounded):
        raise ValueError(f"make_deterministic_actor needs a Bounded action spec, got {type(action_spec).__name__}.")
    low, high = action_spec.space.low, action_spec.space.high
    action_dim = action_spec.shape[-1] if len(action_spec.shape) else 1
    module = nn.Sequential(_mlp(observation_dim, action_dim, num_cells, activation), BoundedTanh(low, high))
    return Actor(module, in_keys=list(in_keys), out_keys=[out_key], spec=action_spec)


def make_tanh_normal_actor(
    observation_dim: int, action_spec: Bounded, *, num_cells: Sequence[int] = (256, 256), activation: type[nn.Module] = nn.ReLU
) -> ProbabilisticActor:
    """A stochastic actor ``a ~ TanhNormal(μ(x), σ(x))`` inside the box of ``action_spec`` (for CQL and IQL).

    An MLP writes ``2m`` numbers, :class:`~tensordict.nn.NormalParamExtractor` splits them into ``"loc"`` and a
    positive ``"scale"``; :class:`~torchrl.modules.TanhNormal` squashes into ``[low, high]``. In deterministic mode
    (evaluation) the action is the squashed location ``low + (high − low)(tanh(μ) + 1) / 2``.
    """
    action_dim = action_spec.shape[-1]
    net = nn.Sequential(
        MLP(in_features=observation_dim, out_features=2 * action_dim, num_cells=list(num_cells),
            activation_class=activation),
        NormalParamExtractor(),
    )
    module = TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"])
    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        spec=action_spec,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": action_spec.space.low, "high": action_spec.space.high},
        default_interaction_type=ExplorationType.RANDOM,
    )
