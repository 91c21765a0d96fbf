"""Network builders: a Q network on (observation, action), a discrete Q head, a bounded deterministic actor.

All builders return ordinary TorchRL modules (:class:`~torchrl.modules.ValueOperator`,
:class:`~torchrl.modules.QValueActor`, :class:`~torchrl.modules.Actor`), so they plug into TorchRL losses, collectors
and :class:`~torchrl_wbrm.objectives.WeightedBellmanLoss` alike.

Every builder takes the same network options: ``num_cells`` (widths; its length is the depth), ``activation`` (a
:mod:`torch.nn` activation class or its name, e.g. ``"SiLU"``, see :func:`resolve_activation`), ``layer_norm``
(a :class:`torch.nn.LayerNorm` after each hidden linear layer) and an optional fixed input normalisation
``(x − loc) / scale`` of the observation (``observation_loc``, ``observation_scale``). Q networks also take
``num_members`` (an ensemble of independently initialised MLPs, reduced by ``"mean"`` or ``"min"``) and
``value_scale`` (Q = ``value_scale`` · MLP: the network learns Q in units of ``value_scale``).

The paper's theory (Section 4) is stated for ReLU networks, but Q* of the LQR task is a quadratic: a smooth
activation fits it, and its gradient in the action (which the actor follows), far better. The recipe's default is
SiLU for Q; the builders' own default stays ReLU.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Bounded, Categorical, OneHot, TensorSpec
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torchrl.envs.utils import ExplorationType
from torchrl.modules import MLP, Actor, ProbabilisticActor, QValueActor, TanhNormal, ValueOperator

__all__ = [
    "ACTIVATIONS",
    "BoundedTanh",
    "EnsembleReduction",
    "NormalisedMLP",
    "build_mlp",
    "initial_q_value",
    "make_deterministic_actor",
    "make_discrete_q_network",
    "make_q_network",
    "make_tanh_normal_actor",
    "resolve_activation",
]

#: The names :func:`resolve_activation` accepts: every elementwise activation of :mod:`torch.nn` (case-insensitive).
ACTIVATIONS = tuple(
    name for name in nn.modules.activation.__all__
    if name not in ("MultiheadAttention", "Softmax", "Softmin", "Softmax2d", "LogSoftmax", "GLU", "Threshold")
)
ENSEMBLE_REDUCTIONS = ("mean", "min")


def resolve_activation(activation: str | type[nn.Module], *, key: str = "activation") -> type[nn.Module]:
    """The :mod:`torch.nn` activation class named ``activation`` (``"SiLU"``, ``"silu"``, ``"ReLU"``, ...), or the
    class itself. An unknown name raises a ``ValueError`` that names ``key`` and lists the known names.

    Examples:
        >>> resolve_activation("silu")
        <class 'torch.nn.modules.activation.SiLU'>
    """
    if isinstance(activation, type) and issubclass(activation, nn.Module):
        return activation
    if isinstance(activation, str):
        by_lower = {name.lower(): name for name in ACTIVATIONS}
        name = by_lower.get(activation.lower())
        if name is not None:
            return getattr(nn, name)
    raise ValueError(f"{key}={activation!r} is not a torch.nn activation: choose one of {list(ACTIVATIONS)}.")


def build_mlp(
    in_features: int,
    out_features: int,
    *,
    num_cells: Sequence[int] = (256, 256),
    activation: str | type[nn.Module] = nn.ReLU,
    layer_norm: bool = False,
) -> MLP:
    """torchrl's :class:`~torchrl.modules.MLP` with the project's network options (hidden ``num_cells``, an
    activation class or name, a :class:`torch.nn.LayerNorm` after each hidden linear layer with ``layer_norm``)."""
    num_cells = [int(c) for c in num_cells]
    if any(c <= 0 for c in num_cells):
        raise ValueError(f"num_cells must hold positive widths, got {num_cells}.")
    norm = {}
    if layer_norm and num_cells:
        norm = {"norm_class": nn.LayerNorm, "norm_kwargs": [{"normalized_shape": c} for c in num_cells]}
    return MLP(in_features=in_features, out_features=out_features, num_cells=num_cells,
               activation_class=resolve_activation(activation), **norm)


class EnsembleReduction(nn.Module):
    """``reduce_k f_k(x)`` over independently initialised members ``f_k`` (``"mean"`` or ``"min"``, elementwise).

    Used as a Q network, the reduced value is *the* Q everywhere (data term, bootstrap target and actor), so a
    ``"mean"`` ensemble averages out the members' initialisation noise and ``"min"`` is a pessimistic estimate.
    """

    def __init__(self, members: Sequence[nn.Module], reduction: str = "mean") -> None:
        super().__init__()
        if reduction not in ENSEMBLE_REDUCTIONS:
            raise ValueError(f"ensemble reduction must be one of {ENSEMBLE_REDUCTIONS}, got {reduction!r}.")
        if len(members) < 1:
            raise ValueError("An ensemble needs at least one member.")
        self.members = nn.ModuleList(members)
        self.reduction = reduction

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        values = torch.stack([member(*inputs) for member in self.members])
        return values.mean(0) if self.reduction == "mean" else values.amin(0)

    def extra_repr(self) -> str:
        return f"reduction={self.reduction!r}"


class NormalisedMLP(nn.Module):
    """``output_scale · net((cat(inputs) − loc) / scale)``: a fixed affine map of the concatenated inputs in front of
    ``net`` and a fixed scale behind it (buffers, not trained; saved in the state dict).

    ``loc``/``scale`` cover the observation coordinates; coordinates past them (the action) pass unchanged.
    """

    def __init__(self, net: nn.Module, *, loc: torch.Tensor | None = None, scale: torch.Tensor | None = None,
                 in_features: int, output_scale: float = 1.0) -> None:
        super().__init__()
        self.net = net
        full_loc, full_scale = torch.zeros(in_features), torch.ones(in_features)
        if loc is not None:
            loc = torch.as_tensor(loc, dtype=torch.get_default_dtype()).reshape(-1)
            scale = torch.as_tensor(scale, dtype=torch.get_default_dtype()).reshape(-1)
            if loc.shape != scale.shape or loc.numel() > in_features:
                raise ValueError(f"observation_loc {tuple(loc.shape)} and observation_scale {tuple(scale.shape)} must "
                                 f"have the same shape, of at most {in_features} features.")
            if not (torch.isfinite(loc).all() and torch.isfinite(scale).all() and (scale > 0).all()):
                raise ValueError(f"observation_loc must be finite and observation_scale finite and > 0, got {loc} "
                                 f"and {scale}.")
            full_loc[: loc.numel()], full_scale[: scale.numel()] = loc, scale
        if not (output_scale > 0 and torch.isfinite(torch.tensor(float(output_scale)))):
            raise ValueError(f"value_scale must be finite and > 0, got {output_scale!r}.")
        self.register_buffer("loc", full_loc)
        self.register_buffer("scale", full_scale)
        self.output_scale = float(output_scale)

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        x = torch.cat(inputs, -1) if len(inputs) > 1 else inputs[0]
        out = self.net((x - self.loc) / self.scale)
        return out * self.output_scale if self.output_scale != 1.0 else out

    def extra_repr(self) -> str:
        return f"output_scale={self.output_scale}"


def _set_output_bias(mlp: MLP, initial_bias: float) -> None:
    """Start the last layer's bias at ``initial_bias``.

    Offline Q targets are of order mean(r)/(1 − γ) (about 100 on the LQR task with γ = 0.9); a network starting at 0
    spends thousands of steps moving its constant.
    """
    last = mlp[-1]
    if not isinstance(last, nn.Linear) or last.bias is None:
        raise ValueError(f"Expected the MLP to end with a biased nn.Linear, got {type(last).__name__}.")
    with torch.no_grad():
        last.bias.fill_(float(initial_bias))


def _network(
    in_features: int,
    out_features: int,
    *,
    num_cells: Sequence[int],
    activation,
    layer_norm: bool,
    initial_bias: float | None = None,
    num_members: int = 1,
    ensemble_reduction: str = "mean",
    value_scale: float = 1.0,
    observation_loc=None,
    observation_scale=None,
) -> nn.Module:
    """The MLP (or ensemble of MLPs) of every builder, behind the optional fixed input normalisation and output
    scale. The output bias starts at ``initial_bias / value_scale`` so that the network starts at ``initial_bias``."""
    if int(num_members) < 1:
        raise ValueError(f"num_members must be >= 1, got {num_members!r}.")
    if (observation_loc is None) != (observation_scale is None):
        raise ValueError("Pass both observation_loc and observation_scale, or neither.")
    members = []
    for _ in range(int(num_members)):
        mlp = build_mlp(in_features, out_features, num_cells=num_cells, activation=activation, layer_norm=layer_norm)
        if initial_bias is not None:
            _set_output_bias(mlp, initial_bias / value_scale)
        members.append(mlp)
    net = members[0] if len(members) == 1 else EnsembleReduction(members, ensemble_reduction)
    if observation_loc is None and value_scale == 1.0:
        return net
    return NormalisedMLP(net, loc=observation_loc, scale=observation_scale, in_features=in_features,
                         output_scale=value_scale)


def make_q_network(
    observation_dim: int,
    action_dim: int,
    *,
    num_cells: Sequence[int] = (256, 256),
    activation: str | type[nn.Module] = nn.ReLU,
    layer_norm: bool = False,
    initial_bias: float | None = None,
    num_members: int = 1,
    ensemble_reduction: str = "mean",
    value_scale: float = 1.0,
    observation_loc: torch.Tensor | None = None,
    observation_scale: torch.Tensor | None = None,
    in_keys: Sequence[NestedKey] = ("observation", "action"),
    out_key: NestedKey = "state_action_value",
) -> ValueOperator:
    """A Q network ``Q(x, a)`` on the concatenated (observation, action), written to ``"state_action_value"``.

    Args:
        observation_dim (int): size of the (flat) observation.
        action_dim (int): size of the (flat) action.

    Keyword Args:
        num_cells (sequence of int): hidden layer widths (their number is the depth). Defaults to ``(256, 256)``.
        activation (type or str): hidden activation class or its :mod:`torch.nn` name (:func:`resolve_activation`).
            Defaults to :class:`torch.nn.ReLU`.
        layer_norm (bool): a ``LayerNorm`` after each hidden linear layer. Defaults to ``False``.
        initial_bias (float): starting value of Q's constant; required. Use ``mean(r) / (1 − γ)`` of the data
            (:func:`initial_q_value`), so that Q starts at the scale of its targets: a Q that starts far from them
            (0 for LQR rewards of mean ≈ 9.6 at γ = 0.9, where the targets are ≈ 96) can blow up in an
            offline loop with an actor (``WeightedBellmanLoss`` then warns). ``0.0`` suits rewards centred on 0.
        num_members (int): independently initialised MLPs whose outputs are reduced (:class:`EnsembleReduction`).
            Defaults to ``1``.
        ensemble_reduction (str): ``"mean"`` or ``"min"`` over the members. Defaults to ``"mean"``.
        value_scale (float): Q = ``value_scale`` · MLP (the network's own outputs are in units of ``value_scale``).
            Defaults to ``1.0``.
        observation_loc, observation_scale (Tensor, optional): a fixed normalisation ``(x − loc) / scale`` of the
            observation before the MLP (e.g. the dataset's mean and standard deviation). Defaults to none.
        in_keys (sequence of NestedKey): the observation and action keys, concatenated in this order.
        out_key (NestedKey): where Q is written. Defaults to ``"state_action_value"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> rewards = torch.full((100, 1), 2.0)
        >>> q = make_q_network(3, 2, num_cells=(16,), initial_bias=initial_q_value(rewards, gamma=0.9))
        >>> td = TensorDict({"observation": torch.zeros(5, 3), "action": torch.zeros(5, 2)}, [5])
        >>> q(td)["state_action_value"].shape
        torch.Size([5, 1])
    """
    if initial_bias is None:
        raise TypeError(
            "make_q_network needs initial_bias, the value Q starts at: mean(r) / (1 − γ) of the data "
            "(initial_q_value(data, gamma)), or 0.0 for rewards centred on 0. A Q far below its targets can blow up "
            "in an offline loop."
        )
    net = _network(
        observation_dim + action_dim, 1, num_cells=num_cells, activation=activation, layer_norm=layer_norm,
        initial_bias=initial_bias, num_members=num_members, ensemble_reduction=ensemble_reduction,
        value_scale=value_scale, observation_loc=observation_loc, observation_scale=observation_scale,
    )
    return ValueOperator(net, in_keys=list(in_keys), out_keys=[out_key])


def initial_q_value(data, gamma: float, *, reward_key: NestedKey = ("next", "reward")) -> float:
    """``mean(r) / (1 − γ)``: the discounted value of the data's mean reward, where a Q network should start
    (``make_q_network(..., initial_bias=initial_q_value(data, gamma))``).

    Args:
        data: the rewards (a tensor), a TensorDict holding them under ``reward_key``, or a torchrl replay buffer
            (its whole storage is read).
        gamma (float): the discount, in ``[0, 1)``.

    Keyword Args:
        reward_key (NestedKey): where a TensorDict or replay buffer holds the reward. Defaults to
            ``("next", "reward")``.

    Examples:
        >>> import torch
        >>> initial_q_value(torch.tensor([1.0, 3.0]), gamma=0.5)  # mean 2, over 1 − γ
        4.0
    """
    try:
        gamma = float(gamma)
    except (TypeError, ValueError):
        raise ValueError(f"gamma must be a number in [0, 1), got {gamma!r}.") from None
    if not 0.0 <= gamma < 1.0:
        raise ValueError(f"gamma must lie in [0, 1) for mean(r) / (1 − γ) to be finite, got {gamma!r}.")
    if isinstance(data, torch.Tensor):
        reward = data
    else:
        from torchrl.data import ReplayBuffer

        if isinstance(data, ReplayBuffer):
            if len(data) == 0:
                raise ValueError("The replay buffer is empty: there are no rewards to average.")
            data = data[:]
        reward = data.get(reward_key, None)
        if reward is None:
            raise KeyError(f"Missing key {reward_key!r} (the reward); the data hold "
                           f"{sorted(str(k) for k in data.keys(True, True))}.")
    if reward.numel() == 0:
        raise ValueError("There are no rewards to average (an empty tensor).")
    mean = float(reward.double().mean())
    if not math.isfinite(mean):
        raise ValueError(f"The rewards' mean is {mean}: they hold non-finite values.")
    return mean / (1.0 - gamma)


def make_discrete_q_network(
    observation_dim: int,
    num_actions: int,
    *,
    action_space: str = "one-hot",
    num_cells: Sequence[int] = (256, 256),
    activation: str | type[nn.Module] = nn.ReLU,
    layer_norm: bool = False,
    initial_bias: float = 0.0,
    num_members: int = 1,
    ensemble_reduction: str = "mean",
    value_scale: float = 1.0,
    observation_loc: torch.Tensor | None = None,
    observation_scale: torch.Tensor | None = None,
    in_keys: Sequence[NestedKey] = ("observation",),
) -> QValueActor:
    """A discrete Q head ``x ↦ (Q(x, a))_a``: a :class:`~torchrl.modules.QValueActor` writing ``"action_value"``.

    The actor also writes the greedy ``"action"`` and its ``"chosen_action_value"``, exactly as TorchRL's DQN expects.

    Args:
        observation_dim (int): size of the (flat) observation.
        num_actions (int): number of discrete actions.

    Keyword Args:
        action_space (str): ``"one-hot"`` (default) or ``"categorical"``: how actions are encoded.
        num_cells, activation, layer_norm, initial_bias, num_members, ensemble_reduction, value_scale,
        observation_loc, observation_scale, in_keys: as in :func:`make_q_network`.

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
    net = _network(
        observation_dim, num_actions, num_cells=num_cells, activation=activation, layer_norm=layer_norm,
        initial_bias=initial_bias, num_members=num_members, ensemble_reduction=ensemble_reduction,
        value_scale=value_scale, observation_loc=observation_loc, observation_scale=observation_scale,
    )
    return QValueActor(net, in_keys=list(in_keys), spec=spec)


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
    activation: str | type[nn.Module] = nn.ReLU,
    layer_norm: bool = False,
    observation_loc: torch.Tensor | None = None,
    observation_scale: torch.Tensor | None = None,
    in_keys: Sequence[NestedKey] = ("observation",),
    out_key: NestedKey = "action",
) -> Actor:
    """A deterministic actor ``μ(x)`` whose output lies inside the bounds of ``action_spec`` (a ``Bounded`` spec).

    The action is ``low + (high − low) · (tanh(u) + 1) / 2`` with ``u`` the MLP's output, so it never leaves the box;
    at initialisation it sits near the centre of the box. ``num_cells``, ``activation``, ``layer_norm``,
    ``observation_loc`` and ``observation_scale`` are as in :func:`make_q_network`.

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
    net = _network(observation_dim, action_dim, num_cells=num_cells, activation=activation, layer_norm=layer_norm,
                   observation_loc=observation_loc, observation_scale=observation_scale)
    module = nn.Sequential(net, BoundedTanh(low, high))
    return Actor(module, in_keys=list(in_keys), out_keys=[out_key], spec=action_spec)


def make_tanh_normal_actor(
    observation_dim: int,
    action_spec: Bounded,
    *,
    num_cells: Sequence[int] = (256, 256),
    activation: str | type[nn.Module] = nn.ReLU,
    layer_norm: bool = False,
    observation_loc: torch.Tensor | None = None,
    observation_scale: torch.Tensor | None = None,
) -> ProbabilisticActor:
    """A stochastic actor ``a ~ TanhNormal(μ(x), σ(x))`` inside the box of ``action_spec`` (for CQL and IQL).

    An MLP writes ``2m`` numbers, :class:`~tensordict.nn.NormalParamExtractor` splits them into ``"loc"`` and a
    positive ``"scale"``; :class:`~torchrl.modules.TanhNormal` squashes into ``[low, high]``. In deterministic mode
    (evaluation) the action is the squashed location ``low + (high − low)(tanh(μ) + 1) / 2``. The network options
    are as in :func:`make_q_network`.
    """
    action_dim = action_spec.shape[-1]
    net = nn.Sequential(
        _network(observation_dim, 2 * action_dim, num_cells=num_cells, activation=activation, layer_norm=layer_norm,
                 observation_loc=observation_loc, observation_scale=observation_scale),
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
