"""The checkpoint format: what a checkpoint holds (:func:`checkpoint_state`), writing it atomically
(:func:`write_checkpoint`), reading it (:func:`read_checkpoint`: ``torch.load(weights_only=True)``, so reading one
never runs code; a corrupted checkpoint, or a file that is not one, is a clear error naming the file), restoring the
training state from it (:func:`restore_training_state`) and the random states it carries (:func:`get_rng_state`,
:func:`set_rng_state`).
"""
from __future__ import annotations

import copy
import hashlib
import pickle
import random
import pickletools
import re
import warnings
import zipfile
from pathlib import Path

import numpy as np
import torch

from torchrl_wbrm.training.results import atomic_write
from torchrl_wbrm.training.stops import TrainingDiverged, non_finite_parameter

__all__ = ["CHECKPOINT_KEYS", "checkpoint_state", "data_fingerprint", "get_rng_state", "read_checkpoint",
           "restore_training_state", "set_rng_state", "set_seed", "write_checkpoint"]


#: Keys of a checkpoint written by :func:`checkpoint_state`.
CHECKPOINT_KEYS = ("state", "history", "rng", "q_loss", "optimisers", "schedulers", "config", "data_fingerprint")


def set_seed(seed: int) -> None:
    """Seed Python's, NumPy's and torch's global generators."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def get_rng_state() -> dict:
    """torch's, NumPy's and Python's global random states, as tensors and primitives only (NumPy's array becomes an
    ``int64`` tensor), so a checkpoint holding them reads with ``torch.load(weights_only=True)``. Where this process
    has used CUDA (``device=cuda``: batches drawn, noise and random actions sampled on the device), each CUDA
    device's generator state too (``"cuda"``)."""
    name, keys, pos, has_gauss, cached_gaussian = np.random.get_state()
    numpy_state = {"name": str(name), "keys": torch.from_numpy(keys.astype(np.int64)), "pos": int(pos),
                   "has_gauss": int(has_gauss), "cached_gaussian": float(cached_gaussian)}
    state = {"torch": torch.get_rng_state(), "numpy": numpy_state, "python": random.getstate()}
    if torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    """Restore :func:`get_rng_state`'s states."""
    torch.set_rng_state(state["torch"])
    numpy_state = state["numpy"]
    np.random.set_state((numpy_state["name"], numpy_state["keys"].numpy().astype(np.uint32), numpy_state["pos"],
                         numpy_state["has_gauss"], numpy_state["cached_gaussian"]))
    random.setstate(state["python"])
    if "cuda" in state:
        if not torch.cuda.is_available() or torch.cuda.device_count() < len(state["cuda"]):
            raise RuntimeError(f"Cannot restore the random state of {len(state['cuda'])} CUDA device(s) saved with "
                               f"this checkpoint: this machine has {torch.cuda.device_count()}.")
        torch.cuda.set_rng_state_all(state["cuda"])


def checkpoint_state(*, state: dict, history: list, q_loss, optimisers: dict, schedulers: dict,
                     data_fingerprint: str, config: dict, selection=None, ratio_fitter=None) -> dict:
    """What a checkpoint holds: the stage and step, the history, the random states, stage 2's loss, optimisers and
    schedules, the data's fingerprint, the config, ``q.select``'s best and last parameters (``selection``, a
    :class:`~torchrl_wbrm.training.selection.Selection`) and stage 1's fitter (its loss, optimiser, best state and
    step count)."""
    sd = {
        "state": dict(state),
        "history": copy.deepcopy(history),
        "rng": get_rng_state(),
        "q_loss": q_loss.state_dict(),
        "optimisers": {name: optimiser.state_dict() for name, optimiser in optimisers.items()},
        "schedulers": {name: scheduler.state_dict() for name, scheduler in schedulers.items()},
        "data_fingerprint": data_fingerprint,
        "config": config,
        "q_best": None if selection is None else selection.best,
        "q_last": None if selection is None else selection.last_state,
    }
    if ratio_fitter is not None:
        fitter = ratio_fitter.state_dict()
        sd.update(ratio_loss=fitter["loss_module"], ratio_optim=fitter["optimizer"], ratio_best=fitter["best"],
                  ratio_steps=fitter["num_steps"])
    return sd


def write_checkpoint(path: Path, sd: dict, *, modules=(), claim=None) -> None:
    """Write ``sd`` to ``path`` atomically: a fresh temporary file beside it, fsynced, then renamed over it. Refused
    (:class:`~torchrl_wbrm.training.stops.TrainingDiverged`, at ``sd``'s stage and step) where a parameter of
    ``modules`` (stage 2's loss, stage 1's fitter's) is not finite, so the checkpoint on disk is always the last finite
    one; ``claim``: the run directory's claim, checked present (nothing is written into a directory made anew)."""
    bad = non_finite_parameter(*modules)
    if bad is not None:
        raise TrainingDiverged(sd["state"]["stage"], sd["state"]["step"], f"parameter {bad}", float("nan"))
    if claim is not None:
        claim.check_present()
    atomic_write(path, lambda f: torch.save(sd, f), tmp=path.with_suffix(".tmp"))


def restore_training_state(sd: dict, path: Path, *, data_fingerprint: str, q_loss, optimisers: dict, schedulers: dict,
                           ratio_fitter=None) -> None:
    """Load a checkpoint's (``sd``, read by :func:`read_checkpoint` from ``path``) stage-2 loss, optimisers and
    schedules and stage 1's fitter into the run's own; refused, naming ``path``, where its data are not the run's (its
    ``data_fingerprint``, :func:`data_fingerprint`). The random states are restored apart (:func:`set_rng_state`),
    once everything else is built."""
    if sd["data_fingerprint"] != data_fingerprint:
        raise ValueError(f"Cannot resume from {path}: its data differ from the data this config reads now (the "
                         f"SHA-256 of every tensor of D, S^b and S^e differs: the dataset's files changed, or the "
                         f"env or seed); a resume never mixes two datasets. Start a new run on these data.")
    q_loss.load_state_dict(sd["q_loss"])
    for name, optimiser in optimisers.items():
        optimiser.load_state_dict(sd["optimisers"][name])
    for name, scheduler in schedulers.items():
        scheduler.load_state_dict(sd["schedulers"][name])
    if ratio_fitter is not None:
        ratio_fitter.load_state_dict({"loss_module": sd["ratio_loss"], "optimizer": sd["ratio_optim"],
                                      "best": sd["ratio_best"], "num_steps": sd.get("ratio_steps", 0)})


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
    names = _pickle_globals(path)
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
    are built, so reading a file never runs code it names. A file that names anything else (a crafted pickle, or a
    NumPy array) is refused, unread, as not a checkpoint this project wrote; a damaged one is a ``RuntimeError``
    naming the file. Both are one line."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Cannot resume: no {path.name} in {path.parent}.")
    try:
        with warnings.catch_warnings():
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
                               f"{type(sd[key]).__name__}, not a {kind.__name__}.")
    state = sd["state"]
    if not (isinstance(state.get("stage"), str) and isinstance(state.get("step"), int)):
        raise RuntimeError(f"Cannot resume: {path} is not a checkpoint this project wrote: its 'state' is {state!r}, "
                           f"not a stage and a step.")
    return sd


#: the type of each entry of a checkpoint :func:`checkpoint_state` writes
_CHECKPOINT_TYPES = {"state": dict, "history": list, "rng": dict, "q_loss": dict, "optimisers": dict,
                     "schedulers": dict, "config": dict, "data_fingerprint": str}


def data_fingerprint(datasets) -> str:
    """The SHA-256 of every tensor of a run's data (``D``, ``S^b`` and ``S^e`` of an
    :class:`~torchrl_wbrm.data.OfflineDatasets`): each entry's name, dtype, shape and bytes, in a fixed order. A
    checkpoint records it, and a resume on data that differ in any value (a reward changed in the dataset's files,
    another env or seed) is refused (:func:`restore_training_state`)."""
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
