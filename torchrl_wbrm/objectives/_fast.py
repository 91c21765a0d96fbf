"""Calling a loss's networks on tensors, and a soft target update over flat tensor lists.

TorchRL's losses hold each network as a parameter-less ("meta") module plus a ``TensorDictParams``, and call it as
``with params.to_module(net): net(TensorDict(...))``. Per call that costs a TensorDict build, the ``to_module`` swap
and the ``TensorDictModule`` output path (in tensordict 0.14 ``TensorDict.from_any`` runs an
``importlib.util.find_spec("pandas")`` on every output), a large share of a step on small networks
(:doc:`/performance`). :class:`NetworkCall` is the one way the losses call a network: for a plain
:class:`~tensordict.nn.TensorDictModule` (``ValueOperator``, a non-``safe`` ``Actor``, ``DensityRatioNetwork``: one
output key, no ``method``, no keyword inputs, no hooks on the wrapper) it puts the same parameter tensors in the same
module slots with plain dictionary assignments and calls ``net.module`` on the input tensors, so the result, its
gradient and the random draws are those of the TensorDict call (tested); for any other module (a
``TensorDictSequential``, a probabilistic or safe actor) it makes that TensorDict call.

The tensors are read, at each call, from the TensorDict the parameters hold at that moment: the one that
``params.to_module(loss)`` puts into a loss's ``TensorDictParams`` (TorchRL's functional and ``torch.vmap`` ensemble
idiom) as well as the loss's own. A ``TensorDictParams``' registered ``nn.Parameter`` entries are not read: they
stay the loss's own while ``to_module`` has put other tensors in.
"""
from __future__ import annotations

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictParams
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

    __slots__ = ("network", "module", "slots", "tree", "out_key", "in_keys", "direct", "why")

    def __init__(self, network, params, out_key, *, why: str = "the network's output", direct: bool = True):
        self.network = network
        self.why = why
        self.module = getattr(network, "module", None)
        self.out_key = out_key
        self.in_keys = list(network.in_keys)
        self.slots = self._slots(network, params, out_key) if direct else None
        self.tree = _nested(self.slots) if self.slots is not None else None
        self.direct = self.slots is not None

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
    def _slots(cls, network, params, out_key) -> dict[str, tuple[dict, str]] | None:
        """The module slot of each entry of ``params``, or ``None`` where the TensorDict call is needed: a network
        that is not plain, another output key, or an entry of ``params`` that names no slot (or a slot no entry
        covers)."""
        if not cls.is_plain(network) or list(network.out_keys) != [out_key]:
            return None
        if not isinstance(params, TensorDictParams):
            return None
        wanted = {name for name, _ in network.named_parameters(remove_duplicate=False)}
        wanted |= {name for name, _ in network.named_buffers(remove_duplicate=False)}
        slots: dict[str, tuple[dict, str]] = {}
        for name in dict(params.named_parameters(recurse=False, remove_duplicate=False)) | dict(
                params.named_buffers(recurse=False, remove_duplicate=False)):
            path, _, attr = name.rpartition(".")
            try:
                module = network.get_submodule(path)
            except AttributeError:
                return None
            # the slot itself is the submodule's own dictionary, written at each call (a public call per entry, e.g.
            # torch.func.functional_call, costs more than 5% of a 2×64 critic step)
            if attr in dict(module.named_parameters(prefix="", recurse=False)):
                slots[name] = (module._parameters, attr)
            elif attr in dict(module.named_buffers(prefix="", recurse=False)):
                slots[name] = (module._buffers, attr)
            else:
                return None
        if set(slots) != wanted:
            return None
        return slots

    def __call__(self, params, inputs, batch_size, *, detach: bool = False) -> torch.Tensor:
        if self.slots is None:
            if isinstance(params, dict):  # dotted names -> tensors (named_tensors), e.g. one critic inside a vmap
                params = TensorDict(params, batch_size=[]).unflatten_keys(".")
            td = TensorDict({key: inputs[key] for key in self.in_keys}, batch_size=batch_size)
            with (params.detach() if detach else params).to_module(self.network, preserve_module_state=False):
                out = self.network(td)
            return get_entry(out, self.out_key, self.why)
        saved = []
        try:
            if isinstance(params, dict):  # dotted names -> tensors (named_tensors)
                slots = self.slots
                for name, value in params.items():
                    _swap(slots[name], value, saved, detach)
            else:  # the TensorDict the parameters hold now (the one to_module put in, if any), level by level
                _install(self.tree, params, saved, detach)
            return self.module(*[inputs[key] for key in self.in_keys])
        finally:
            for container, attr, old in saved:
                container[attr] = old


def _nested(slots: dict) -> dict:
    """The flat ``{dotted name: slot}`` as nested dictionaries, one level per TensorDict level."""
    tree: dict = {}
    for name, slot in slots.items():
        *path, attr = name.split(".")
        level = tree
        for key in path:
            level = level.setdefault(key, {})
        level[attr] = slot
    return tree


def _install(tree: dict, params, saved: list, detach: bool) -> None:
    """Put each tensor of the TensorDict ``params`` into its slot of ``tree`` (nested as ``params``), recording the
    slot's previous value in ``saved``."""
    for key, value in params.items():
        slot = tree[key]
        if type(slot) is dict:
            _install(slot, value, saved, detach)
            continue
        _swap(slot, value, saved, detach)


def _swap(slot: tuple, value, saved: list, detach: bool) -> None:
    """Put ``value`` (detached with ``detach``) into the module slot ``(container, attr)``, recording the slot's
    previous value in ``saved``."""
    container, attr = slot
    saved.append((container, attr, container[attr]))
    container[attr] = value.detach() if detach and value is not None else value


def named_tensors(params) -> dict:
    """``{dotted name: tensor}`` of a loss's parameters (a ``TensorDictParams`` or any TensorDict), the same tensors
    (no copy, gradients flow): a plain pytree that ``torch.vmap`` maps over, and that :class:`NetworkCall` takes.

    Read level by level from the TensorDict the parameters hold now: for a loss's ``TensorDictParams``, the one
    ``params.to_module(loss)`` put in, if any, not its registered ``nn.Parameter`` entries (which stay the loss's
    own)."""
    out: dict = {}
    _flatten(params, "", out)
    return out


def _flatten(params, prefix: str, out: dict) -> None:
    for key, value in params.items():
        if isinstance(value, torch.Tensor) or value is None:
            out[prefix + key] = value
        else:
            _flatten(value, f"{prefix}{key}.", out)


class ForeachSoftUpdate(SoftUpdate):
    """torchrl's :class:`~torchrl.objectives.SoftUpdate` (same construction, checks and update
    ``θ' ← θ' + (1 − ε)(θ − θ')``, with ``1 − ε`` computed as torchrl does), stepped as one ``torch._foreach_lerp_``
    over flat lists of the target and source tensors instead of a TensorDict walk per network.

    The pairs are torchrl's own (``init_`` keeps only the targets distinct from their sources); the tensors are read
    from the loss's ``TensorDictParams`` at every step (``TensorDict.get``, about 2 µs a tensor), so a replaced
    parameter (``.to(device)``) is picked up. Bitwise the same update as ``SoftUpdate`` (tested).
    """

    def _pairs(self) -> list[tuple]:
        """``(source TensorDictParams, target TensorDictParams, key)`` of each pair torchrl's ``init_`` kept."""
        pairs = self.__dict__.get("_foreach_pairs")
        if pairs is None:
            pairs = []
            for key in self._sources.keys(True, True):
                key = key if isinstance(key, tuple) else (key,)
                pairs.append((getattr(self.loss_module, key[0]), getattr(self.loss_module, "target_" + key[0]),
                              key[1:]))
            self.__dict__["_foreach_pairs"] = pairs
        return pairs

    def step(self) -> None:
        if not self.initialized:
            raise Exception(
                f"{self.__class__.__name__} must be initialized (`{self.__class__.__name__}.init_()`) before "
                "calling step()"
            )
        sources, targets = [], []
        for source, target_params, key in self._pairs():
            target = target_params.get(key)
            if target.requires_grad:
                raise RuntimeError("the target parameter is part of a graph.")
            sources.append(source.get(key))
            targets.append(target)
        with torch.no_grad():  # (the tensors themselves rather than 24 ``.data`` views: the same kernel on the same memory)
            torch._foreach_lerp_(targets, sources, 1 - self.eps)
