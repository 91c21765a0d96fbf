"""ŵ over a dataset, computed once in chunks, shaped, and stored next to the transitions.

Stored under ``"density_ratio"`` it is the weight :class:`~torchrl_wbrm.objectives.WeightedBellmanLoss` reads; under
``"priority_weight"`` it is the per-sample weight TorchRL's own losses (``TD3BCLoss``, ``TD3Loss``, ``DDPGLoss``,
``DQNLoss``, ``SACLoss``, ``IQLLoss``, ...) multiply their per-sample losses by (``use_prioritized_weights="auto"``),
which turns any of them into a ŵ-weighted method. (TorchRL reduces a weighted loss as ``Σ wᵢ lᵢ / Σ wᵢ`` over the
batch. A replay buffer with a ``PrioritizedSampler`` writes its own ``"priority_weight"`` into every batch: there,
store ŵ under another key and point the loss at it with ``loss.set_keys(priority_weight=...)``.)
"""
from __future__ import annotations

import torch
from tensordict import MemoryMappedTensor, TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torchrl.data import ReplayBuffer
from torchrl.data.replay_buffers.storages import TensorStorage

from torchrl_wbrm.ratio.fitting import as_tensordict
from torchrl_wbrm.ratio.weights import shape_weights

__all__ = ["NonFiniteWeightsError", "compute_density_ratio", "store_density_ratio"]


class NonFiniteWeightsError(ValueError):
    """Shaped weights that are not all finite (``value``: the first bad one); nothing was stored."""

    def __init__(self, key, value: float):
        self.key, self.value = key, value
        super().__init__(f"The weights to store under {key!r} are not all finite (e.g. {value}); nothing was stored.")


@torch.no_grad()
def compute_density_ratio(
    ratio_network: TensorDictModule,
    data: TensorDictBase | ReplayBuffer,
    *,
    chunk_size: int = 8192,
    device: torch.device | str | None = None,
    out_key: NestedKey | None = None,
) -> torch.Tensor:
    """``ratio_network`` over every row of ``data`` (a TensorDict or a replay buffer's storage), ``chunk_size`` rows at
    a time on ``device`` (defaults to the network's); returns the network's output for all rows, on the CPU
    (``[N, 1]`` for a :class:`~torchrl_wbrm.modules.DensityRatioNetwork`). Only the network's ``in_keys`` are read."""
    if chunk_size <= 0:
        raise ValueError(f"chunk_size must be > 0, got {chunk_size}.")
    td = as_tensordict(data).select(*ratio_network.in_keys)
    out_key = out_key if out_key is not None else ratio_network.out_keys[0]
    if device is None:
        param = next(iter(ratio_network.parameters()), None)
        device = param.device if param is not None else td.device
    return torch.cat([ratio_network(chunk.to(device))[out_key] for chunk in td.split(chunk_size)]).cpu()


def store_density_ratio(
    target: TensorDictBase | ReplayBuffer,
    weights: torch.Tensor | None = None,
    *,
    ratio_network: TensorDictModule | None = None,
    key: NestedKey = "density_ratio",
    temper: float = 1.0,
    clip: float | None = None,
    mix: float = 0.0,
    self_normalise: bool = True,
    keepdim: bool = False,
    dtype: torch.dtype | None = None,
    chunk_size: int = 8192,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    r"""Store per-sample weights over ``target`` under ``key``, shaped by :func:`~torchrl_wbrm.ratio.shape_weights`.

    Args:
        target: a TensorDict (the entry is set on it) or a torchrl replay buffer over a 1-d ``TensorStorage``
            (``LazyTensorStorage``, ``LazyMemmapStorage``): the entry is added to its storage, so every later
            ``sample()`` carries it.
        weights (Tensor, optional): raw weights, one per row (e.g. an exact ratio). Without them ``ratio_network``
            is run over ``target`` (:func:`compute_density_ratio`).

    Keyword Args:
        ratio_network (TensorDictModule, optional): the fitted ŵ (e.g. ``DensityRatioFit.network``).
        key (NestedKey): where the weights go: ``"density_ratio"`` (default; read by ``WeightedBellmanLoss``) or
            ``"priority_weight"`` (read by TorchRL's losses).
        temper, clip, mix, self_normalise: the shaping ``ŵ^temper``, ``min(·, clip)``, ``(1 − mix)·/mean + mix``
            and division by the mean over the dataset (defaults: none but the self-normalisation).
        keepdim (bool): store shape ``[N, 1]`` instead of ``[N]``. TorchRL's losses need ``[N]`` (the shape of
            their per-sample losses); ``WeightedBellmanLoss`` takes either. Defaults to ``False``.
        dtype (torch.dtype, optional): the stored dtype (defaults to that of the weights).
        chunk_size (int), device: for :func:`compute_density_ratio`.

    Returns: the stored weights (``[N]`` or ``[N, 1]``, on the CPU). Raises :class:`NonFiniteWeightsError` (a
    ``ValueError``) and stores nothing if the shaped weights are not all finite.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> from torchrl_wbrm.ratio import store_density_ratio
        >>> rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=8)
        >>> _ = rb.extend(TensorDict({"observation": torch.randn(4, 2)}, [4]))
        >>> store_density_ratio(rb, torch.tensor([1.0, 2.0, 3.0, 2.0]), key="priority_weight")
        tensor([0.5000, 1.0000, 1.5000, 1.0000])
        >>> rb.sample()["priority_weight"].shape
        torch.Size([8])
    """
    if isinstance(target, ReplayBuffer):
        storage = target.storage
        if not isinstance(storage, TensorStorage) or storage.ndim != 1:
            raise TypeError(f"store_density_ratio needs a replay buffer over a 1-d TensorStorage, got "
                            f"{type(storage).__name__}.")
        n = len(storage)
        rows = storage._storage[:n]
    elif isinstance(target, TensorDictBase):
        n, rows = target.shape[0], target
    else:
        raise TypeError(f"Expected a TensorDict or a torchrl ReplayBuffer, got {type(target).__name__}.")
    if weights is None:
        if ratio_network is None:
            raise ValueError("Pass the raw weights or a ratio_network to compute them.")
        weights = compute_density_ratio(ratio_network, rows, chunk_size=chunk_size, device=device)
    elif ratio_network is not None:
        raise ValueError("Pass the raw weights or a ratio_network, not both.")
    if weights.numel() != n:
        raise ValueError(f"Got {weights.numel()} weights for {n} rows.")
    w = shape_weights(weights, temper=temper, clip=clip, mix=mix, self_normalise=self_normalise)
    if not bool(torch.isfinite(w).all()):
        raise NonFiniteWeightsError(key, float(w[~torch.isfinite(w)][0]))
    w = w.reshape(n, 1) if keepdim else w.reshape(n)
    if dtype is not None:
        w = w.to(dtype)
    if isinstance(target, TensorDictBase):
        target.set(key, w)
        return w
    data = storage._storage
    if key in data.keys(True, True):  # overwrite in place (works on a locked, memory-mapped storage too)
        data.get(key)[:n] = w.to(data.get(key).dtype).reshape(data.get(key)[:n].shape)
        return w
    full = torch.zeros((data.shape[0], *w.shape[1:]), dtype=w.dtype)
    full[:n] = w
    locked = data.is_locked
    if locked:  # a memory-mapped storage: the new entry is memory-mapped too
        data.unlock_()
        full = MemoryMappedTensor.from_tensor(full)
    try:
        data.set(key, full.to(data.device) if data.device is not None and not locked else full)
    finally:
        if locked:
            data.lock_()
    return w
