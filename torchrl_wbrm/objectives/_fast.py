"""The losses' hot path without TensorDict bookkeeping: calling a functional network on tensors, and a soft target
update over flat tensor lists.

TorchRL's losses hold each network as a parameter-less ("meta") module plus a ``TensorDictParams``, and call it as
``with params.to_module(net): net(TensorDict(...))``. Per call that costs a TensorDict build, the ``to_module`` swap
and the ``TensorDictModule`` output path (in tensordict 0.14 ``TensorDict.from_any`` runs an
``importlib.util.find_spec("pandas")`` on every output); on the project's 2×256 networks at batch 256 it was a third
of a critic step. :class:`FunctionalCall` does the same computation with plain dictionary assignments: the same
parameter tensors are put in the same module slots and ``net.module`` is called on the same input tensors, so the
result, its gradient and the random draws are identical (tested against the TensorDict path).

It applies to a plain :class:`~tensordict.nn.TensorDictModule` (``ValueOperator``, a non-``safe`` ``Actor``,
``DensityRatioNetwork``): one output key, no ``method``, no keyword inputs, no hooks on the wrapper. Anything else
(a ``TensorDictSequential``, a probabilistic actor, a safe actor) gets ``None`` from :meth:`FunctionalCall.build`
and keeps the TensorDict path.
"""
from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule, TensorDictParams
from torch import nn
from torchrl.objectives import SoftUpdate

__all__ = ["FunctionalCall", "ForeachSoftUpdate"]


class FunctionalCall:
    """``network.module(*tensors)`` with the entries of a ``TensorDictParams`` placed in the module's slots.

    Build it with :meth:`build` (``None`` where the network is not a plain ``TensorDictModule``); call it as
    ``call(params, *tensors, detach=False)``. ``detach=True`` puts detached views in (no gradient reaches the
    parameters, it still reaches the inputs), as ``params.detach().to_module(...)`` does.
    """

    __slots__ = ("network", "module", "slots")

    def __init__(self, network: TensorDictModule, slots: dict[str, tuple[dict, str]]):
        self.network = network
        self.module = network.module
        self.slots = slots

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
    def build(cls, network, params) -> "FunctionalCall | None":
        """The fast call of ``network`` (a loss's meta module) for ``params`` (its ``TensorDictParams``), or ``None``.

        Every entry of ``params`` must name a parameter or buffer slot of ``network`` and every slot of ``network``
        must be covered, or the TensorDict path is kept.
        """
        if not cls.is_plain(network):
            return None
        if not isinstance(params, TensorDictParams):
            return None
        stores = (params._parameters, params._buffers)
        wanted = {name for name, _ in network.named_parameters(remove_duplicate=False)}
        wanted |= {name for name, _ in network.named_buffers(remove_duplicate=False)}
        slots: dict[str, tuple[dict, str]] = {}
        for store in stores:
            for name in store:
                *path, attr = name.split(".")
                module: nn.Module = network
                try:
                    for part in path:
                        module = module._modules[part]
                except KeyError:
                    return None
                if attr in module._parameters:
                    slots[name] = (module._parameters, attr)
                elif attr in module._buffers:
                    slots[name] = (module._buffers, attr)
                else:
                    return None
        if set(slots) != wanted:
            return None
        return cls(network, slots)

    def __call__(self, params, *tensors: torch.Tensor, detach: bool = False) -> torch.Tensor:
        saved = []
        slots = self.slots
        try:
            for name, value in _entries(params):
                container, attr = slots[name]
                saved.append((container, attr, container[attr]))
                container[attr] = value.detach() if detach and value is not None else value
            return self.module(*tensors)
        finally:
            for container, attr, old in saved:
                container[attr] = old


def _entries(params):
    """``(dotted name, tensor)`` of a ``TensorDictParams`` (its registered parameters and buffers: two dict walks) or
    of any other TensorDict (e.g. the detached online parameters TorchRL hands out for a target that does not
    exist)."""
    if isinstance(params, TensorDictParams):
        yield from params._parameters.items()
        yield from params._buffers.items()
    else:
        for key, value in params.items(True, True):
            yield (".".join(key) if isinstance(key, tuple) else key), value


class ForeachSoftUpdate(SoftUpdate):
    """torchrl's :class:`~torchrl.objectives.SoftUpdate` (same construction, checks and update
    ``θ' ← θ' + (1 − ε)(θ − θ')``, with ``1 − ε`` computed as torchrl does), stepped as one ``torch._foreach_lerp_``
    over flat lists of the target and source tensors instead of a TensorDict walk per network.

    The pairs are torchrl's own (``init_`` keeps only the targets distinct from their sources); the tensors are read
    from the loss's ``TensorDictParams`` at every step (dictionary lookups), so a replaced parameter (``.to(device)``)
    is picked up. Bitwise the same update as ``SoftUpdate`` (tested).
    """

    def _slots(self) -> list[tuple[dict, dict, str]]:
        slots = self.__dict__.get("_foreach_slots")
        if slots is None:
            slots = []
            for key in self._sources.keys(True, True):
                key = key if isinstance(key, tuple) else (key,)
                source = getattr(self.loss_module, key[0])
                target = getattr(self.loss_module, "target_" + key[0])
                name = ".".join(key[1:])
                src_store = source._parameters if name in source._parameters else source._buffers
                dst_store = target._buffers if name in target._buffers else target._parameters
                slots.append((src_store, dst_store, name))
            self.__dict__["_foreach_slots"] = slots
        return slots

    def step(self) -> None:
        if not self.initialized:
            raise Exception(
                f"{self.__class__.__name__} must be initialized (`{self.__class__.__name__}.init_()`) before "
                "calling step()"
            )
        sources, targets = [], []
        for src_store, dst_store, name in self._slots():
            target = dst_store[name]
            if target.requires_grad:
                raise RuntimeError("the target parameter is part of a graph.")
            sources.append(src_store[name])
            targets.append(target)
        with torch.no_grad():  # (the tensors themselves rather than 24 ``.data`` views: the same kernel on the same memory)
            torch._foreach_lerp_(targets, sources, 1 - self.eps)
