"""Batch draws from the offline replay buffers without the buffer's per-call bookkeeping: D's batches and the paired
S^b/S^e batches of stage 1.

``TensorDictReplayBuffer.sample()`` draws its indices with one ``torch.randint`` and then spends most of its time in
TensorDict machinery (the sampler/writer protocol, an ``"index"`` entry, a device cast), four times the indexing
itself on the recipe's batches (``docs/performance.md``).

:class:`BufferBatches` draws the *same* indices (the same ``torch.randint`` call on the same generator, so a run draws
the same batches as through ``buffer.sample()``; tested) and gathers every entry of the storage with
``torch.index_select(..., out=...)`` into tensors allocated once (on the training device, so a device-resident
buffer is sampled without a host sync). Each call wraps them in a fresh TensorDict shell, so a loss that writes an
entry into its batch cannot leak it into the next one. The tensors are overwritten by the next draw: a batch is
valid until the next ``sample()``. :class:`PairedSampler` draws stage 1's paired batches the same way: the behaviour
indices, then the expert ones, each from its own buffer's generator, as the two buffers' ``sample()`` draw them.
"""
from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import TensorDictReplayBuffer
from torchrl.data.replay_buffers.samplers import RandomSampler

from torchrl_wbrm.keys import BEHAVIOUR, EXPERT

__all__ = ["BufferBatches", "PairedSampler", "STATE_ACTION_KEYS"]

#: The entries of S^b and S^e the density ratio reads.
STATE_ACTION_KEYS = ("observation", "action")


class BufferBatches:
    """Uniform batches of ``batch_size`` from ``buffer``'s storage, drawn as its ``RandomSampler`` draws them.

    Args:
        buffer: a ``TensorDictReplayBuffer`` with a ``RandomSampler`` over a 1-d storage (``LazyTensorStorage`` or
            ``LazyMemmapStorage``).
        batch_size: the batch size (defaults to the buffer's).

    Keyword Args:
        device: where the batch lives (defaults to the storage's device).
        exclude: storage entries not copied into the batch.
    """

    def __init__(self, buffer: TensorDictReplayBuffer, batch_size: int | None = None, *, device=None,
                 exclude=("index",)):
        if type(buffer.sampler) is not RandomSampler:
            raise TypeError(f"BufferBatches needs a RandomSampler, got {type(buffer.sampler).__name__}.")
        storage = buffer.storage
        if storage.ndim != 1:
            raise ValueError(f"BufferBatches needs a 1-d storage, got ndim={storage.ndim}.")
        batch_size = batch_size if batch_size is not None else buffer.batch_size
        if batch_size is None or batch_size <= 0:
            raise ValueError(f"batch_size must be > 0, got {batch_size!r}.")
        self.storage, self.sampler = storage, buffer.sampler
        self.batch_size = int(batch_size)
        data: TensorDictBase = storage[:]  # the stored rows (views: nothing is copied)
        self.length = len(storage)
        self.index_device = getattr(storage, "device", None)
        self.device = torch.device(device) if device is not None else data.device
        keys = [k for k in data.keys(True, True) if (k if isinstance(k, str) else k[0]) not in exclude]
        self._keys = keys
        # entries on another device than the batch's are moved there once (a host buffer trained on CUDA)
        self._sources = [data.get(k).to(self.device) for k in keys]
        self._outputs = [torch.empty((self.batch_size, *s.shape[1:]), dtype=s.dtype, device=self.device)
                         for s in self._sources]
        # indices on the host for a host batch (RandomSampler's draw, bit for bit); on an accelerator they are drawn
        # there, from its default generator, so that sampling never waits for the device
        self._draw_on_batch_device = self.device.type != "cpu" and torch.device(self.index_device or "cpu") != self.device
        # the batch's nesting, ("next", "reward") under "next": {name: output index or a sub-tree}
        self._tree: dict = {}
        for i, key in enumerate(keys):
            *path, last = (key,) if isinstance(key, str) else key
            node = self._tree
            for part in path:
                node = node.setdefault(part, {})
            node[last] = i
        self._batch_size = torch.Size([self.batch_size])

    def indices(self) -> torch.Tensor:
        """The next batch's indices: ``RandomSampler``'s own draw (its ``sample``) for a host batch."""
        if self._draw_on_batch_device:
            return torch.randint(0, self.length, (self.batch_size,), device=self.device)
        return self.sampler.sample(self.storage, self.batch_size)[0]

    def gather(self, index: torch.Tensor) -> TensorDict:
        index = index.to(self.device)
        for source, out in zip(self._sources, self._outputs):
            torch.index_select(source, 0, index, out=out)
        return TensorDict(self._entries(self._tree), batch_size=self._batch_size, device=self.device)

    def _entries(self, tree: dict) -> dict:
        """The output tensors nested as ``tree`` (TensorDict's constructor nests the sub-dicts)."""
        outputs = self._outputs
        return {name: outputs[node] if type(node) is int else self._entries(node) for name, node in tree.items()}

    def sample(self) -> TensorDict:
        return self.gather(self.indices())


class PairedSampler:
    """``TensorDict({"behaviour": S^b batch, "expert": S^e batch})`` of the state-action keys, ``batch_size`` rows each.

    The behaviour indices are drawn first, then the expert ones, each as its buffer's ``RandomSampler`` draws them
    (its ``sample()``, bit for bit): a fixed seed gives the same stream of batches whichever code asks for them. A
    batch is overwritten by the next ``sample()``; ``clone()`` it to keep it.

    Args:
        behaviour: S^b's ``TensorDictReplayBuffer`` (a ``RandomSampler`` over a 1-d storage).
        expert: S^e's.
        batch_size: rows drawn from each.

    Keyword Args:
        keys: the entries drawn (defaults to ``("observation", "action")``).
        device: where the batch lives (defaults to the storage's device).
    """

    def __init__(self, behaviour: TensorDictReplayBuffer, expert: TensorDictReplayBuffer, batch_size: int, *,
                 keys=STATE_ACTION_KEYS, device=None):
        if batch_size <= 0:
            raise ValueError(f"batch_size must be > 0, got {batch_size}.")
        keep = {k if isinstance(k, str) else k[0] for k in keys}  # top-level names (a nested key keeps its head)
        self.batch_size = int(batch_size)
        self._sides = {}
        for name, buffer in ((BEHAVIOUR, behaviour), (EXPERT, expert)):
            data = buffer.storage[:]
            exclude = tuple(k for k in data.keys() if k not in keep)
            self._sides[name] = BufferBatches(buffer, self.batch_size, device=device, exclude=exclude)
        self.device = self._sides[BEHAVIOUR].device

    def sample(self) -> TensorDict:
        index = {name: side.indices() for name, side in self._sides.items()}
        return TensorDict({name: side.gather(index[name]) for name, side in self._sides.items()},
                          batch_size=[self.batch_size],
                          device=self.device)
