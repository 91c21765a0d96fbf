"""An action rescaling between an env's action box and ``[−1, 1]ᵐ``, the convention of torchrl's offline losses.

torchrl's ``CQLLoss`` draws its random actions uniformly in ``[−1, 1]ᵐ`` (with density ``0.5ᵐ``), TD3+BC's target
smoothing noise and its cloning term are in the paper's normalised action units, and d3rlpy rescales every continuous
action to ``[−1, 1]`` (``MinMaxActionScaler``). An algorithm that works in those units keeps its policy and Q in
``[−1, 1]ᵐ`` and maps

- the data's actions into it once, before they enter the replay buffer (:meth:`ActionScaling.scale_data`: the
  trainer's ``Algo.map_data``),
- the actor's output back to the box for the env (:meth:`ActionScaling.policy`: the evaluated policy),
- the box actions at which Q̂ is read back to unit actions (:meth:`ActionScaling.q_reader`),
- and Q's input: the losses give Q unit actions, and :meth:`ActionScaling.unit_q_network` maps them back to the box
  before the network's first layer (a fixed affine input layer: Q keeps the function class of a network on box
  actions).

The map is affine per coordinate, ``u = (a − c) / h`` with ``c = (high + low) / 2`` and ``h = (high − low) / 2``,
so it is exact up to float rounding and the same for every seed (it holds no state but the box).
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.data import Bounded
from torchrl.modules import ValueOperator

from torchrl_wbrm._devices import device_of

__all__ = ["ActionScaling", "BoxActionInput", "FromUnitAction"]


class FromUnitAction(nn.Module):
    """``u ↦ c + h · u``: a unit action to the box (a module, so the evaluated policy is one TensorDict pipeline)."""

    def __init__(self, centre: torch.Tensor, half_width: torch.Tensor):
        super().__init__()
        self.register_buffer("centre", centre.clone())
        self.register_buffer("half_width", half_width.clone())

    def forward(self, unit_action: torch.Tensor) -> torch.Tensor:
        return self.centre + self.half_width * unit_action


class BoxActionInput(nn.Module):
    """``(x, u) ↦ net(x, c + h · u)``: a Q network on box actions read with unit actions (a fixed input layer)."""

    def __init__(self, net: nn.Module, centre: torch.Tensor, half_width: torch.Tensor):
        super().__init__()
        self.net = net
        self.to_box = FromUnitAction(centre, half_width)

    def forward(self, observation: torch.Tensor, unit_action: torch.Tensor) -> torch.Tensor:
        return self.net(observation, self.to_box(unit_action))


class ActionScaling:
    """The affine map between the box ``[low, high]`` of a ``Bounded`` action spec and ``[−1, 1]ᵐ``.

    Examples:
        >>> import torch
        >>> from torchrl.data import Bounded
        >>> scaling = ActionScaling.from_spec(Bounded(-5.0, 5.0, (2,)))
        >>> scaling.to_unit(torch.tensor([5.0, -2.5])).tolist()
        [1.0, -0.5]
        >>> scaling.from_unit(torch.tensor([-1.0, 0.5])).tolist()
        [-5.0, 2.5]
        >>> scaling.unit_spec.space.low.tolist(), scaling.unit_spec.space.high.tolist()
        ([-1.0, -1.0], [1.0, 1.0])
    """

    def __init__(self, spec: Bounded, action_key: str = "action"):
        if not isinstance(spec, Bounded):
            raise ValueError(f"ActionScaling needs a Bounded action spec, got {type(spec).__name__}.")
        low, high = spec.space.low, spec.space.high
        if not bool(torch.isfinite(low).all() and torch.isfinite(high).all() and (high > low).all()):
            raise ValueError(f"ActionScaling needs a finite box with high > low, got low={low}, high={high}.")
        self.spec = spec
        self.action_key = action_key
        self.centre = (high + low) / 2
        self.half_width = (high - low) / 2
        self.unit_spec = Bounded(-torch.ones_like(low), torch.ones_like(high), shape=spec.shape, dtype=spec.dtype,
                                 device=spec.device)

    @classmethod
    def from_spec(cls, spec: Bounded, action_key: str = "action") -> "ActionScaling":
        return cls(spec, action_key)

    def to_unit(self, action: torch.Tensor) -> torch.Tensor:
        """Box action ``a`` -> unit action ``(a − c) / h`` (the box's corners go to ``±1``)."""
        return (action - self.centre.to(action)) / self.half_width.to(action)

    def from_unit(self, unit_action: torch.Tensor) -> torch.Tensor:
        """Unit action ``u`` -> box action ``c + h u``."""
        return self.centre.to(unit_action) + self.half_width.to(unit_action) * unit_action

    def scale_data(self, data: TensorDictBase) -> TensorDictBase:
        """A shallow copy of ``data`` whose action entry is in unit actions (the trainer's ``Algo.map_data``)."""
        return data.clone(False).set(self.action_key, self.to_unit(data[self.action_key]))

    def policy(self, actor: TensorDictModuleBase) -> TensorDictSequential:
        """``actor`` (acting in unit actions) followed by the map to the box: what the env runs."""
        to_box = TensorDictModule(FromUnitAction(self.centre, self.half_width).to(device_of(actor) or "cpu"),
                                  in_keys=[self.action_key], out_keys=[self.action_key])
        return TensorDictSequential(actor, to_box)

    def unit_q_network(self, q_network: ValueOperator) -> ValueOperator:
        """``q_network`` (of ``(observation, action)`` in the box) read with unit actions: its interface is the unit
        box, as the losses need, while the network itself still sees box actions (the same function class; only the
        first layer's input is rescaled, as ``q.normalise_observations`` rescales the observations)."""
        in_keys, out_keys = list(q_network.in_keys), list(q_network.out_keys)
        if len(in_keys) != 2:
            raise ValueError(f"unit_q_network needs a Q network of (observation, action), got in_keys={in_keys}.")
        box_input = BoxActionInput(q_network.module, self.centre, self.half_width)
        # the map's constants go where the network is: a Q network built on an accelerator stays there
        return ValueOperator(box_input.to(device_of(q_network) or "cpu"), in_keys=in_keys, out_keys=out_keys)

    def q_reader(self, q_value):
        """Wrap a reader ``q_value(td) -> (Q̂, action)`` of a unit-action Q so it reads ``td``'s box actions."""

        def read(td: TensorDictBase):
            q, _ = q_value(self.scale_data(td))
            return q, td[self.action_key]

        return read
