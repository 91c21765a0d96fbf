"""ŵ over a dataset, computed once in chunks, shaped, and stored next to the transitions.

Stored under ``"density_ratio"`` it is the weight :class:`~torchrl_wbrm.objectives.WeightedBellmanLoss` and
:class:`~torchrl_wbrm.objectives.WeightedLoss` read. Any TorchRL loss built with ``reduction="none"`` becomes
ŵ-weighted inside ``WeightedLoss(loss)``, which reduces each per-sample term as ``Σ ŵᵢ lᵢ / Σ ŵᵢ``: ``IQLLoss``,
``CQLLoss``, ``DiscreteCQLLoss`` and ``BCLoss`` need WeightedLoss, since they ignore ``"priority_weight"``.

Stored under ``"priority_weight"`` it is the per-sample weight of the TorchRL losses that read ``"priority_weight"``
themselves (``DDPGLoss``, ``DQNLoss``, ``DistributionalDQNLoss``, ``SACLoss``, ``DiscreteSACLoss``, ``TD3Loss``,
``TD3BCLoss``, ``TQCLoss``: :data:`~torchrl_wbrm.objectives.NATIVE_PRIORITY_WEIGHT_LOSSES`), with
``use_prioritized_weights="auto"``; they reduce it the same way. No other TorchRL loss reads that key: there a weight
stored under it is silently ignored. (A replay buffer with a ``PrioritizedSampler`` writes its own
``"priority_weight"`` into every batch: there, store ŵ under ``"density_ratio"`` and use ``WeightedLoss``, which
multiplies the two.)

The weights live in the buffer's storage beside the rows they belong to. Rows written later by ``extend`` (or
``add``) carry no weight of their own: such rows hold NaN under the key, and ``WeightedLoss`` and
``WeightedBellmanLoss`` refuse a batch holding them, naming the key; store the weights again after writing.
"""
from __future__ import annotations

import warnings

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torchrl.data import ReplayBuffer
from torchrl.data.replay_buffers.storages import TensorStorage
from torchrl.envs.transforms import Transform

from torchrl_wbrm.keys import DENSITY_RATIO
from torchrl_wbrm.objectives.functional import effective_sample_size
from torchrl_wbrm.ratio.fitting import as_tensordict
from torchrl_wbrm.ratio.weights import shape_weights

#: Below this share of the rows, the stored weights' effective sample size ``(Σw)² / Σw²`` draws a warning.
TINY_ESS_FRACTION = 0.01

__all__ = ["TINY_ESS_FRACTION", "MissingWeightsError", "NonFiniteWeightsError", "StoredWeightsFollowRows", "compute_density_ratio",
           "store_density_ratio"]


class NonFiniteWeightsError(ValueError):
    """Shaped weights that are not all finite (``value``: the first bad one); nothing was stored."""

    def __init__(self, key, value: float):
        self.key, self.value = key, value
        super().__init__(f"The weights to store under {key!r} are not all finite (e.g. {value}); nothing was stored.")


class MissingWeightsError(ValueError):
    """Rows sampled from a replay buffer that hold no stored weight: they were written after the weights were."""


class StoredWeightsFollowRows(Transform):
    """Keeps the weights that :func:`store_density_ratio` stored in a replay buffer with the rows they belong to.

    :func:`store_density_ratio` appends it to the buffer (``buffer.append_transform``). On every write (``extend``,
    ``add``, ``buffer[i] = ...``; the inverse transform) a row that comes without ``key`` gets NaN there, so a row
    that replaces an old one never inherits the old row's weight. On every read (``sample``, ``buffer[i]``) a batch
    holding such a row is refused with a :class:`MissingWeightsError` naming the key and the fix (call
    :func:`store_density_ratio` again over the buffer). Rows written with their own ``key`` keep it.

    Args:
        key (NestedKey): the key of the stored weights.
        row_shape (torch.Size): the shape of one row's weight (``()`` or ``(1,)``).
        dtype (torch.dtype): the stored dtype.
    """

    def __init__(self, key: NestedKey, row_shape: torch.Size, dtype: torch.dtype) -> None:
        super().__init__(in_keys=[], out_keys=[])
        self.key, self.row_shape, self.dtype = key, torch.Size(row_shape), dtype

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        weight = tensordict.get(self.key, None)
        if weight is not None and weight.is_floating_point():
            missing = torch.isnan(weight)
            if bool(missing.any()):
                rows = missing.reshape(*tensordict.batch_size, -1).any(-1).nonzero().reshape(-1).tolist()
                raise MissingWeightsError(
                    f"{len(rows)} sampled row(s) hold no stored weight under {self.key!r} (batch positions "
                    f"{rows[:8]}{' ...' if len(rows) > 8 else ''}): they were written to the buffer after "
                    f"store_density_ratio stored the weights. Call store_density_ratio(buffer, ...) again after "
                    "writing, or write rows with their own weight under that key."
                )
        return tensordict

    _call = forward

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        if tensordict.get(self.key, None) is None:
            tensordict.set(self.key, torch.full((*tensordict.batch_size, *self.row_shape), float("nan"),
                                                dtype=self.dtype, device=tensordict.device))
        return tensordict

    def __repr__(self) -> str:
        return f"{type(self).__name__}(key={self.key!r})"


def _follow_rows(buffer: ReplayBuffer, key: NestedKey, row_shape: torch.Size, dtype: torch.dtype) -> None:
    """Append :class:`StoredWeightsFollowRows` for ``key`` to ``buffer`` unless it already has one."""
    transform = buffer.transform
    existing = list(transform) if transform is not None else []
    if any(isinstance(t, StoredWeightsFollowRows) and t.key == key for t in existing):
        return
    buffer.append_transform(StoredWeightsFollowRows(key, row_shape, dtype))


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
    rows = as_tensordict(data)
    missing = [key for key in ratio_network.in_keys if key not in rows.keys(True, True)]
    if missing:
        raise KeyError(f"The ratio network reads {missing}, which the data do not hold (their keys: "
                       f"{sorted(map(str, rows.keys(True, True)))}).")
    td = rows.select(*ratio_network.in_keys)
    out_key = out_key if out_key is not None else ratio_network.out_keys[0]
    if device is None:
        param = next(iter(ratio_network.parameters()), None)
        device = param.device if param is not None else td.device
    try:
        return torch.cat([ratio_network(chunk.to(device))[out_key] for chunk in td.split(chunk_size)]).cpu()
    except RuntimeError as err:
        if "shapes cannot be multiplied" not in str(err) and "size mismatch" not in str(err):
            raise
        widths = {str(key): tuple(td.get(key).shape[td.batch_dims:]) for key in ratio_network.in_keys}
        raise ValueError(f"The ratio network does not take these data: their {', '.join(ratio_network.in_keys)} "
                         f"have the per-row shapes {widths}, and the network fails on them ({str(err).splitlines()[0]}); "
                         f"pass the network fitted on data of these dimensions.") from None


def _warn_if_tiny_ess(w: torch.Tensor, key: NestedKey, temper: float) -> None:
    """A warning when the shaped weights' effective sample size is below :data:`TINY_ESS_FRACTION` of the rows."""
    w = w.reshape(-1).to(torch.float64)
    ess = float(effective_sample_size(w)) if bool((w > 0).any()) else 0.0
    if ess < TINY_ESS_FRACTION * w.numel():
        warnings.warn(
            f"The weights stored under {key!r} have an effective sample size (Σw)²/Σw² of {ess:.1f} for {w.numel()} "
            f"rows ({100 * ess / w.numel():.2g}%): a few rows carry every weighted loss. Flatten them with a temper "
            f"below the {temper:g} used (ratio.temper in the recipe, temper= here; e.g. 0.25) or a clip.",
            UserWarning, stacklevel=3)


def store_density_ratio(
    target: TensorDictBase | ReplayBuffer,
    weights: torch.Tensor | None = None,
    *,
    ratio_network: TensorDictModule | None = None,
    key: NestedKey = DENSITY_RATIO,
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
            (``LazyTensorStorage``, ``LazyMemmapStorage``): the entry is added to its storage (a memory-mapped,
            locked storage takes no new entry, as in torchrl: one that lacks ``key`` is refused, and one that holds
            it has it overwritten in place), so every later ``sample()`` carries it.
        weights (Tensor, optional): raw weights, one per row (e.g. an exact ratio). Without them ``ratio_network``
            is run over ``target`` (:func:`compute_density_ratio`).

    Keyword Args:
        ratio_network (TensorDictModule, optional): the fitted ŵ (e.g. ``DensityRatioFit.network``).
        key (NestedKey): where the weights go: ``"density_ratio"`` (default; read by ``WeightedBellmanLoss`` and
            ``WeightedLoss``) or ``"priority_weight"`` (read only by the TorchRL losses of
            :data:`~torchrl_wbrm.objectives.NATIVE_PRIORITY_WEIGHT_LOSSES`).
        temper, clip, mix, self_normalise: the shaping ``ŵ^temper``, ``min(·, clip)``, ``(1 − mix)·/mean + mix``
            and division by the mean over the dataset (defaults: none but the self-normalisation).
        keepdim (bool): store shape ``[N, 1]`` instead of ``[N]``. TorchRL's losses need ``[N]`` (the shape of
            their per-sample losses); ``WeightedBellmanLoss`` takes either. Defaults to ``False``.
        dtype (torch.dtype, optional): the stored dtype (defaults to that of the weights).
        chunk_size (int), device: for :func:`compute_density_ratio`.

    Returns: the stored weights (``[N]`` or ``[N, 1]``, on the CPU; a multi-dimensional TensorDict ``[*B]`` gets
    ``[*B]`` or ``[*B, 1]``, computed over its flattened rows). Raises :class:`NonFiniteWeightsError` (a
    ``ValueError``) and stores nothing if the shaped weights are not all finite. Warns (``UserWarning``) when their
    effective sample size ``(Σw)²/Σw²`` is below :data:`TINY_ESS_FRACTION` of the rows, naming ``ratio.temper``.
    A replay buffer over a multi-dimensional storage is refused (ValueError); a ratio network built by
    :func:`~torchrl_wbrm.ratio.fit_density_ratio` for categorical index actions reads them as stored.

    In a replay buffer the weights follow their rows (:class:`StoredWeightsFollowRows`, appended to the buffer's
    transforms): a row written later by ``extend`` or ``add`` holds no weight (NaN) until ``store_density_ratio``
    is called again, and a ``sample()`` that draws it raises :class:`MissingWeightsError`, naming the key.

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
        if not isinstance(storage, TensorStorage):
            raise TypeError(f"store_density_ratio needs a replay buffer over a TensorStorage, got "
                            f"{type(storage).__name__}.")
        if storage.ndim != 1:
            raise ValueError(f"store_density_ratio needs a 1-d storage (one row per transition), got a {storage.ndim}-d "
                             f"{type(storage).__name__}: build the buffer with ndim=1, or store into a TensorDict of "
                             "the rows (a multi-dimensional TensorDict is flattened).")
        n = len(storage)
        if n == 0:
            raise ValueError(f"The replay buffer is empty: there are no rows to store weights under {key!r} for; "
                             "extend it with the transitions first.")
        rows = storage[:]  # the stored rows (views)
    elif isinstance(target, TensorDictBase):
        if target.batch_dims == 0 or target.batch_size.numel() == 0:
            raise ValueError(f"The TensorDict has batch size {tuple(target.batch_size)}: there are no rows to store "
                             f"weights under {key!r} for.")
        n, rows = target.batch_size.numel(), as_tensordict(target)  # [episodes, steps]: flattened, one row per sample
    else:
        raise TypeError(f"Expected a TensorDict or a torchrl ReplayBuffer, got {type(target).__name__}.")
    if weights is None:
        if ratio_network is None:
            raise ValueError("Pass the raw weights or a ratio_network to compute them.")
        weights = compute_density_ratio(ratio_network, rows, chunk_size=chunk_size, device=device)
    elif ratio_network is not None:
        raise ValueError("Pass the raw weights or a ratio_network, not both.")
    weights = torch.as_tensor(weights)
    if isinstance(target, TensorDictBase) and target.batch_dims > 1 and weights.shape[:target.batch_dims] == \
            target.batch_size and weights.numel() == n:
        weights = weights.reshape(n)  # one weight per row of a multi-dimensional TensorDict, given in its shape
    if not weights.is_floating_point():  # counts or 0/1 weights: shaped (divided by their mean) as floats
        weights = weights.to(torch.get_default_dtype())
    if tuple(weights.shape) not in ((n,), (n, 1)):
        raise ValueError(f"Got weights of shape {tuple(weights.shape)} for {n} rows; expected one weight per row, "
                         f"shape ({n},) or ({n}, 1).")
    w = shape_weights(weights, temper=temper, clip=clip, mix=mix, self_normalise=self_normalise)
    if not bool(torch.isfinite(w).all()):
        raise NonFiniteWeightsError(key, float(w[~torch.isfinite(w)][0]))
    _warn_if_tiny_ess(w, key, temper)
    w = w.reshape(n, 1) if keepdim else w.reshape(n)
    if dtype is not None:
        w = w.to(dtype)
    if isinstance(target, TensorDictBase):
        w = w.reshape(*target.batch_size, *w.shape[1:])
        target.set(key, w)
        return w
    if key in storage[:].keys(True, True):  # overwrite in place (works on a locked, memory-mapped storage too)
        stored = storage[:].get(key)
        stored[:n] = w.to(stored.dtype).reshape(stored[:n].shape)
        _follow_rows(target, key, stored.shape[1:], stored.dtype)
        return w
    if rows.is_locked:  # a memory-mapped storage takes no new entry (torchrl drops one from its writes)
        raise ValueError(f"The replay buffer's {type(storage).__name__} is locked (memory-mapped) and holds no "
                         f"{key!r} entry, and a locked storage takes no new one: put the entry in the data before the "
                         f"first extend (e.g. data[{key!r}] = torch.ones(len(data))), then store the weights over it.")
    _follow_rows(target, key, w.shape[1:], w.dtype)
    entry = TensorDict({key: w}, batch_size=[n])
    storage.set(slice(0, n), entry if rows.device is None else entry.to(rows.device), set_cursor=False)  # rows 0..n-1
    return w
