"""Calling a loss's networks on tensors, and a soft target update over flat tensor lists.

TorchRL's losses hold each network as a parameter-less ("meta") module plus a ``TensorDictParams``, and call it as
``with params.to_module(net): net(TensorDict(...))``. Per call that costs a TensorDict build, the ``to_module`` swap
and the ``TensorDictModule`` output path (in tensordict 0.14 ``TensorDict.from_any`` runs an
``importlib.util.find_spec("pandas")`` on every output), a large share of a step on small networks
(:doc:`/performance`). :class:`NetworkCall` is the one way the losses call a network: for a plain
:class:`~tensordict.nn.TensorDictModule` (``ValueOperator``, a non-``safe`` ``Actor``, ``DensityRatioNetwork``: one
output key, no ``method``, no keyword inputs, no hooks on the wrapper) it calls ``net.module`` on the input tensors
with the same parameter tensors through :func:`torch.func.functional_call`, so the result, its
gradient and the random draws are those of the TensorDict call (tested); for any other module (a
``TensorDictSequential``, a probabilistic or safe actor) it makes that TensorDict call.
"""
from __future__ import annotations

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictParams
from torch.func import functional_call
from torchrl.objectives import SoftUpdate

from torchrl_wbrm.objectives._utils import get_entry

__all__ = ["ForeachSoftUpdate", "NetworkCall", "named_tensors"]


class NetworkCall:
    """``network(params, inputs) -> output``: a loss's functional network called on tensors.

    Args:
        network (TensorDictModuleBase): the loss's (parameter-less) module, e.g. ``loss.value_network``.
        params (TensorDictParams): its parameters, e.g. ``loss.value_network_params`` (their names, not values, are
            read here: any parameters of the same structure can be passed to each call).
        out_key (NestedKey): the output read.

    Keyword Args:
        why (str): what the output is, for the KeyError when the network does not write ``out_key``.
        direct (bool): call ``network.module`` on the tensors where the network is a plain ``TensorDictModule``
            (``True``, default); ``False`` always makes the TensorDict call. :attr:`direct` tells which is used.

    Called as ``call(params, inputs, batch_size, detach=False)`` with ``inputs`` a mapping from each of the
    network's in_keys to a tensor whose leading dimensions are ``batch_size``. ``detach=True`` puts detached
    parameters in (no gradient reaches them; it still reaches the inputs), as ``params.detach().to_module(...)``.
    """

    __slots__ = ("network", "module", "names", "out_key", "in_keys", "direct", "why")

    def __init__(self, network, params, out_key, *, why: str = "the network's output", direct: bool = True):
        self.network = network
        self.why = why
        self.module = getattr(network, "module", None)
        self.out_key = out_key
        self.in_keys = list(network.in_keys)
        self.names = self._names(network, params, out_key) if direct else None
        self.direct = self.names is not None

    @staticmethod
    def is_plain(network) -> bool:
        """A ``TensorDictModule`` whose forward is exactly ``out_keys[0] <- module(*in_keys tensors)``."""
        if not isinstance(network, TensorDictModule):
            return False
        from torchrl.modules.tensordict_module.common import SafeModule

        forward = type(network).forward
        if forward is not TensorDictModule.forward and forward is not SafeModule.forward:
            return False
        return (
            not getattr(network, "safe", False)
            and getattr(network, "method", None) is None
            and not getattr(network, "method_kwargs", None)
            and getattr(network, "_kwargs", None) is None
            and len(network.out_keys) == 1
            and not network._forward_hooks
            and not network._forward_pre_hooks
        )

    @classmethod
    def _names(cls, network, params, out_key) -> dict[str, str] | None:
        """Each entry of ``params`` -> its name inside ``network.module``, or ``None`` where the TensorDict call is
        needed: a network that is not plain, another output key, or entries of ``params`` other than the network's
        parameters and buffers."""
        if not cls.is_plain(network) or list(network.out_keys) != [out_key]:
            return None
        if not isinstance(params, TensorDictParams):
            return None
        wanted = {name for name, _ in network.named_parameters(remove_duplicate=False)}
        wanted |= {name for name, _ in network.named_buffers(remove_duplicate=False)}
        given = [name for name, _ in _entries(params)]
        if set(given) != wanted or len(given) != len(wanted) or not all(n.startswith("module.") for n in given):
            return None
        return {name: name[len("module."):] for name in given}

    def __call__(self, params, inputs, batch_size, *, detach: bool = False) -> torch.Tensor:
        if self.names is None:
            if isinstance(params, dict):  # dotted names -> tensors (named_tensors), e.g. one critic inside a vmap
                params = TensorDict(params, batch_size=[]).unflatten_keys(".")
            td = TensorDict({key: inputs[key] for key in self.in_keys}, batch_size=batch_size)
            with (params.detach() if detach else params).to_module(self.network, preserve_module_state=False):
                out = self.network(td)
            return get_entry(out, self.out_key, self.why)
        names = self.names
        entries = params.items() if isinstance(params, dict) else _entries(params)
        tensors = {names[name]: value.detach() if detach and value is not None else value for name, value in entries}
        return functional_call(self.module, tensors, tuple(inputs[key] for key in self.in_keys), tie_weights=False)


def named_tensors(params) -> dict:
    """``{dotted name: tensor}`` of a loss's parameters (a ``TensorDictParams`` or any TensorDict), the same tensors
    (no copy, gradients flow): a plain pytree that ``torch.vmap`` maps over, and that :class:`NetworkCall` takes."""
    return dict(_entries(params))


def _entries(params):
    """``(dotted name, tensor)`` of a ``TensorDictParams`` (its registered parameters and buffers: two dict walks) or
    of any other TensorDict (e.g. the detached online parameters TorchRL hands out for a target that does not
    exist)."""
    if isinstance(params, TensorDictParams):
        yield from params.named_parameters(remove_duplicate=False)
        yield from params.named_buffers(remove_duplicate=False)
    else:
        for key, value in params.items(True, True):
            yield (".".join(key) if isinstance(key, tuple) else key), value


class ForeachSoftUpdate(SoftUpdate):
    """torchrl's :class:`~torchrl.objectives.SoftUpdate` (same construction, checks and update
    ``θ' ← θ' + (1 − ε)(θ − θ')``, with ``1 − ε`` computed as torchrl does), stepped as one ``torch._foreach_lerp_``
    over flat lists of the target and source tensors instead of a TensorDict walk per network.

    The pairs are torchrl's own (``init_`` keeps only the targets distinct from their sources); the tensors are read
    from the loss's ``TensorDictParams`` at every step (``named_parameters``), so a replaced parameter
    (``.to(device)``) is picked up. Bitwise the same update as ``SoftUpdate`` (tested).
    """

    def _slots(self) -> list[tuple[TensorDictParams, TensorDictParams, list[str]]]:
        """``(source params, target params, the dotted names of torchrl's pairs)`` per network."""
        slots = self.__dict__.get("_foreach_slots")
        if slots is None:
            names: dict[str, list[str]] = {}
            for key in self._sources.keys(True, True):
                key = key if isinstance(key, tuple) else (key,)
                names.setdefault(key[0], []).append(".".join(key[1:]))
            slots = [(getattr(self.loss_module, network), getattr(self.loss_module, "target_" + network), pairs)
                     for network, pairs in names.items()]
            self.__dict__["_foreach_slots"] = slots
        return slots

    def step(self) -> None:
        if not self.initialized:
            raise Exception(
                f"{self.__class__.__name__} must be initialized (`{self.__class__.__name__}.init_()`) before "
                "calling step()"
            )
        sources, targets = [], []
        for source_params, target_params, names in self._slots():
            source, target = dict(_entries(source_params)), dict(_entries(target_params))
            for name in names:
                if target[name].requires_grad:
                    raise RuntimeError("the target parameter is part of a graph.")
                sources.append(source[name])
                targets.append(target[name])
        with torch.no_grad():  # (the tensors themselves rather than 24 ``.data`` views: the same kernel on the same memory)
            torch._foreach_lerp_(targets, sources, 1 - self.eps)
