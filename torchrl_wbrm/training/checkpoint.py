"""Reading a checkpoint: ``torch.load(weights_only=True)``, so reading one never runs code; a corrupted checkpoint,
or a file that is not one, is a clear error naming the file.
"""
from __future__ import annotations

import hashlib
import pickle
import pickletools
import re
import warnings
import zipfile
from pathlib import Path

import numpy as np
import torch

__all__ = ["CHECKPOINT_KEYS", "data_fingerprint", "read_checkpoint", "same_data"]


#: Keys of a checkpoint written by :meth:`WBRMTrainer.state_dict`.
CHECKPOINT_KEYS = ("state", "history", "rng", "q_loss", "config", "data_fingerprint")


def _numpy_array_globals() -> list:
    """NumPy's array reconstruction, allowed to :func:`read_checkpoint`'s restricted unpickler for the one thing a
    checkpoint of an older version holds beyond tensors and primitives: NumPy's random state (an ``uint32`` array).
    These build an array from its bytes and dtype; nothing they touch runs code."""
    multiarray = getattr(np, "_core", None) or np.core
    return [multiarray.multiarray._reconstruct, np.ndarray, np.dtype, type(np.dtype(np.uint32))]


def _pickle_globals(path: Path) -> list[str]:
    """The globals (``module.name``) a pickle file would import when read, listed from its opcodes without running
    any (``torch.save``'s zip archive, or a bare pickle); ``[]`` when they cannot be listed."""
    try:
        return list(torch.serialization.get_unsafe_globals_in_checkpoint(path))
    except Exception:  # noqa: BLE001 (not a zip archive: read it as a bare pickle)
        pass
    names, strings = [], []
    try:
        with open(path, "rb") as f:
            for opcode, arg, _ in pickletools.genops(f):
                if opcode.name == "GLOBAL":
                    names.append(".".join(str(arg).split(" ", 1)))
                elif opcode.name == "STACK_GLOBAL" and len(strings) >= 2:
                    names.append(f"{strings[-2]}.{strings[-1]}")
                elif isinstance(arg, str) and "UNICODE" in opcode.name:
                    strings.append(arg)
    except Exception:  # noqa: BLE001 (damaged: the globals read so far)
        pass
    return list(dict.fromkeys(names))


def _foreign_pickle(path: Path, err: Exception) -> str | None:
    """What the file ``path`` refused by ``torch.load(weights_only=True)`` would do that a checkpoint never does (the
    globals it would import, or a pickle opcode ``torch.save`` does not write), or ``None`` when the refusal is damage
    (bytes that are no pickle opcode)."""
    allowed = {f"{g.__module__}.{g.__qualname__}" for g in _numpy_array_globals()}
    names = [n for n in _pickle_globals(path) if n not in allowed]
    found = re.search(r"Unsupported global: GLOBAL (\S+)", str(err))
    if found or names:
        return f"it would import {', '.join(names or [found.group(1)])} when read"
    found = re.search(r"Unsupported operand (\d+)", str(err))
    if found:
        code = int(found.group(1))
        known = {ord(op.code): op.name for op in pickletools.opcodes if len(op.code) == 1}
        if code in known:
            return f"it is a pickle torch.save does not write (opcode {known[code]})"
    return None


def _first_line(err: Exception) -> str:
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    return f"{type(err).__name__}: {lines[0] if lines else ''}".rstrip(": ")


def read_checkpoint(path: Path) -> dict:
    """A checkpoint, read with ``torch.load(weights_only=True)``: only tensors, primitives and containers of them
    (and an older checkpoint's NumPy random state) are built, so reading a file never runs code it names. A file that
    names anything else (a crafted pickle) is refused, unread, as not a checkpoint this project wrote; a damaged one
    is a ``RuntimeError`` naming the file. Both are one line."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Cannot resume: no {path.name} in {path.parent}.")
    try:
        with warnings.catch_warnings(), torch.serialization.safe_globals(_numpy_array_globals()):
            warnings.simplefilter("ignore")  # torch's note on a pickle protocol it did not write
            sd = torch.load(path, weights_only=True, map_location="cpu")
    except pickle.UnpicklingError as err:
        foreign = _foreign_pickle(path, err)
        if foreign is None:
            raise RuntimeError(
                f"Cannot resume: {path} is corrupted or not a checkpoint ({_first_line(err)}). Start a new run in "
                f"another directory, or pass overwrite=true to replace this one."
            ) from None
        raise RuntimeError(
            f"Cannot resume: {path} is not a checkpoint this project wrote: {foreign}, so it was refused and nothing "
            f"in it ran. Start a new run in another directory, or pass overwrite=true to replace this one."
        ) from None
    except (EOFError, RuntimeError, zipfile.BadZipFile, ValueError, KeyError, AttributeError, ImportError,
            IndexError, TypeError, UnicodeDecodeError, OSError) as err:
        raise RuntimeError(
            f"Cannot resume: {path} is corrupted or not a checkpoint ({_first_line(err)}). Start a new run in "
            f"another directory, or pass overwrite=true to replace this one."
        ) from err
    missing = [k for k in CHECKPOINT_KEYS if not isinstance(sd, dict) or k not in sd]
    if missing:
        raise RuntimeError(f"Cannot resume: {path} is not a complete checkpoint (it lacks {missing}).")
    for key, kind in _CHECKPOINT_TYPES.items():
        if not isinstance(sd[key], kind):
            raise RuntimeError(f"Cannot resume: {path} is not a checkpoint this project wrote: its {key!r} is a "
                               f"{type(sd[key]).__name__}, not a {' or '.join(k.__name__ for k in _as_tuple(kind))}.")
    state = sd["state"]
    if not (isinstance(state.get("stage"), str) and isinstance(state.get("step"), int)):
        raise RuntimeError(f"Cannot resume: {path} is not a checkpoint this project wrote: its 'state' is {state!r}, "
                           f"not a stage and a step.")
    return sd


#: the type of each entry of a checkpoint :meth:`WBRMTrainer.state_dict` writes
_CHECKPOINT_TYPES = {"state": dict, "history": list, "rng": dict, "q_loss": dict, "config": dict,
                     "data_fingerprint": (str, int, float)}


def _as_tuple(kind) -> tuple:
    return kind if isinstance(kind, tuple) else (kind,)


def data_fingerprint(datasets) -> str:
    """The SHA-256 of every tensor of a run's data (``D``, ``S^b`` and ``S^e`` of an
    :class:`~torchrl_wbrm.data.OfflineDatasets`): each entry's name, dtype, shape and bytes, in a fixed order. A
    checkpoint records it, and a resume on data that differ in any value (a reward changed in the dataset's files,
    another env or seed) is refused (:func:`same_data`)."""
    digest = hashlib.sha256()
    for part in ("transitions", "behaviour_samples", "expert_samples"):
        buffer = getattr(datasets, part, None)
        if buffer is None or len(buffer) == 0:
            digest.update(f"{part}/empty".encode())
            continue
        td = buffer[:]
        for key in sorted(td.keys(include_nested=True, leaves_only=True), key=str):
            tensor = td.get(key).detach().cpu().contiguous()
            digest.update(f"{part}/{key}/{tensor.dtype}/{tuple(tensor.shape)}".encode())
            digest.update(tensor.view(torch.uint8).numpy().tobytes() if tensor.numel() else b"")
    return digest.hexdigest()


def same_data(saved, datasets, fingerprint: str | None = None) -> bool:
    """Whether a checkpoint's ``data_fingerprint`` (``saved``) is that of ``datasets``: the SHA-256 of every tensor
    (:func:`data_fingerprint`). A checkpoint of an older version recorded a float, the sum of D's first 100 rows'
    observations and actions; it is compared by that rule (so an older run stays resumable). ``fingerprint``:
    ``datasets``' own, when computed already."""
    if isinstance(saved, str):
        return saved == (fingerprint or data_fingerprint(datasets))
    d = datasets.transitions[:]
    legacy = float(d["observation"][:100].double().sum() + d["action"][:100].double().sum())
    return isinstance(saved, (int, float)) and abs(saved - legacy) <= 1e-6
