"""Input checks shared by the losses: a missing key, a per-sample shape, a sign. """
from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

_REDUCTIONS = ("mean", "sum", "none")


class NonFiniteError(ValueError):
    """An entry holds NaN or ±inf; ``key`` names it. A ValueError, so callers that catch those still do; the trainer
    reads it during training as a divergence (a network's output, since the data are verified finite)."""

    def __init__(self, message: str, key: NestedKey) -> None:
        super().__init__(message)
        self.key = key


def checks_run(enabled: bool, value: torch.Tensor | None) -> bool:
    """Whether a loss's data-dependent input checks (finite values, signs, index ranges: each a host read) run now on
    ``value``, a tensor they read (``None``: absent, so nothing is read back): ``enabled`` (the loss's public
    ``check_inputs`` switch), not inside ``torch.compile`` (the read would break the graph), and ``value`` not
    wrapped by a functorch transform (batched by ``torch.vmap``, or differentiated by ``torch.func.grad``: such a
    tensor cannot be read back). The batch of a ``torch.vmap`` over parameters only (TorchRL's ensemble idiom) is
    plain, so it is checked there too. Shape, key and dtype checks need no host read and always run."""
    if not enabled or torch.compiler.is_compiling():
        return False
    return value is None or torch.func.debug_unwrap(value, recurse=False) is value


def check_reduction(reduction: str | None) -> str:
    """``None`` means ``"mean"``; anything outside ``("mean", "sum", "none")`` is a ValueError."""
    if reduction is None:
        return "mean"
    if reduction not in _REDUCTIONS:
        raise ValueError(f"reduction must be one of {_REDUCTIONS} or None, got {reduction!r}.")
    return reduction


def get_entry(tensordict: TensorDictBase, key: NestedKey, why: str) -> torch.Tensor:
    """``tensordict.get(key)``, or a KeyError that names the key, says why it is needed, and lists what is there."""
    value = tensordict.get(key, None)
    if value is None:
        present = sorted(str(k) for k in tensordict.keys(True, True))
        raise KeyError(f"Missing key {key!r} ({why}). The input holds: {present}.")
    return value


def per_sample(value: torch.Tensor, batch_shape: torch.Size, key: NestedKey) -> torch.Tensor:
    """View a per-sample entry of shape ``[*B]`` or ``[*B, 1]`` as ``[*B]``; any other shape is a ValueError."""
    if value.shape == batch_shape:
        return value
    if value.shape == (*batch_shape, 1):
        return value.squeeze(-1)
    raise ValueError(
        f"Entry {key!r} has shape {tuple(value.shape)}; expected one value per sample, "
        f"i.e. shape {tuple(batch_shape)} or {(*batch_shape, 1)}."
    )


def check_sign(value: torch.Tensor, key: NestedKey, *, strictly_positive: bool) -> None:
    """Raise ValueError if ``value`` has a negative (or, if ``strictly_positive``, a zero) or non-finite entry.

    The check runs on CPU tensors only: on an accelerator it would need a host sync (and ``torch._assert_async``
    leaves a CUDA context unusable after a failure), so there it is skipped.
    """
    if value.device.type != "cpu":
        return
    ok = (value > 0) if strictly_positive else (value >= 0)
    ok = (ok & torch.isfinite(value)).all()
    expected = "strictly positive" if strictly_positive else "non-negative"
    message = f"Entry {key!r} must be finite and {expected}."
    if not bool(ok):
        error = NonFiniteError if not bool(torch.isfinite(value).all()) else ValueError
        args = (key,) if error is NonFiniteError else ()
        raise error(f"{message} Got min {value.min().item():.4g}, max {value.max().item():.4g}.", *args)


def check_not_empty(batch_size: torch.Size, what: str) -> None:
    """A ValueError for an empty batch (a mean over no samples is NaN)."""
    if batch_size.numel() == 0:
        raise ValueError(f"The {what} batch is empty (batch size {tuple(batch_size)}): a loss needs at least one sample.")


def check_finite(value: torch.Tensor, key: NestedKey) -> None:
    """A ValueError naming ``key`` if a floating entry holds NaN or ±inf (CPU tensors only, as :func:`check_sign`)."""
    if value.device.type != "cpu" or not value.is_floating_point():
        return
    finite = torch.isfinite(value)
    if not bool(finite.all()):
        bad = int((~finite).sum())
        raise NonFiniteError(f"Entry {key!r} holds {bad} non-finite value(s) (NaN or inf) of {value.numel()}.", key)


def as_bool_flag(value: torch.Tensor, key: NestedKey, *, check: bool = True) -> torch.Tensor:
    """An episode-end flag as a bool tensor: bool as it is, any integer dtype holding only 0 and 1 converted
    (``~`` on an int64 1 is −2, on a uint8 0 is 255: torchrl's estimators need bools); a float flag or an integer
    other than 0/1 is refused, naming ``key`` (that value check, a host read, runs where ``check``)."""
    if value.dtype == torch.bool:
        return value
    if value.is_floating_point() or value.is_complex():
        raise TypeError(f"Entry {key!r} is an episode-end flag of dtype {value.dtype}; pass bool (or integer 0/1).")
    if check and value.device.type == "cpu" and value.numel() and not bool(((value == 0) | (value == 1)).all()):
        raise ValueError(
            f"Entry {key!r} is an episode-end flag of dtype {value.dtype} with values other than 0 and 1 "
            f"(min {int(value.min())}, max {int(value.max())})."
        )
    return value != 0


def check_same_features(a: torch.Tensor, b: torch.Tensor, key_a, key_b, batch_a: torch.Size, batch_b: torch.Size) -> None:
    """A ValueError naming both keys and both shapes if two entries' per-sample shapes differ."""
    if a.shape[len(batch_a):] != b.shape[len(batch_b):]:
        raise ValueError(
            f"Entry {key_a!r} has shape {tuple(a.shape)} and {key_b!r} has shape {tuple(b.shape)}: their per-sample "
            f"shapes {tuple(a.shape[len(batch_a):])} and {tuple(b.shape[len(batch_b):])} must match."
        )


def input_width(network: torch.nn.Module) -> int | None:
    """The number of input features of ``network`` where its structure shows it: a TensorDict module (or the first
    module of a sequence) around the project's builders (:class:`~torchrl_wbrm.modules.NormalisedMLP`, an ensemble,
    the ratio head) or torchrl's ``MLP`` / ``nn.Sequential`` starting with an ``nn.Linear``; ``None`` for anything
    else (a feature map, a lazy layer, a custom module), which is then not checked."""
    from tensordict.nn import TensorDictModuleBase, TensorDictSequential
    from torch import nn

    from torchrl_wbrm.modules.density_ratio import _RatioHead
    from torchrl_wbrm.modules.networks import EnsembleReduction, NormalisedMLP

    module = network
    for _ in range(16):
        if isinstance(module, nn.Linear):
            return None if isinstance(module, nn.LazyLinear) else int(module.in_features)
        if isinstance(module, TensorDictSequential):
            module = module.module[0] if len(module.module) else None
        elif isinstance(module, TensorDictModuleBase) and isinstance(getattr(module, "module", None), nn.Module):
            module = module.module
        elif isinstance(module, NormalisedMLP):
            module = module.net
        elif isinstance(module, EnsembleReduction):
            module = module.members[0]
        elif isinstance(module, _RatioHead):
            module = module.mlp
        elif isinstance(module, nn.Sequential) and len(module):
            module = module[0]
        else:
            return None
    return None


def check_input_width(width: int | None, entries: dict, batch_size: torch.Size, what: str) -> None:
    """A ValueError naming every input key, its shape and its width when the per-sample widths of ``entries``
    (key -> tensor) do not add up to ``width``, the number of input features of ``what``."""
    if width is None:
        return
    widths = {key: math.prod(value.shape[len(batch_size):]) for key, value in entries.items()}
    if sum(widths.values()) != width:
        given = ", ".join(f"{key!r} of shape {tuple(entries[key].shape)} ({n} feature(s))" for key, n in widths.items())
        raise ValueError(
            f"The {what} reads {width} input feature(s), but the batch gives {sum(widths.values())}: {given}. "
            "The data's observation (and action) widths must match the ones the network was built for."
        )


def check_input_dtype(dtype: torch.dtype | None, entries: dict, what: str) -> None:
    """A TypeError naming the key and both dtypes when a floating input's dtype is not the network's."""
    if dtype is None:
        return
    for key, value in entries.items():
        if value.is_floating_point() and value.dtype != dtype:
            raise TypeError(
                f"Entry {key!r} has dtype {value.dtype} but the {what}'s parameters are {dtype}: cast the batch "
                f"(e.g. batch.to({dtype})) or the networks to one dtype."
            )
