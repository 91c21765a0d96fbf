"""What keeps a run honest: safe run directories, resume checks, divergence detection, signals, strict JSON.

* :func:`claim_run_dir` — one run at a time per run directory: an exclusive advisory lock on the directory itself,
  held for the run (nothing is written for it; the kernel drops it when the process ends).
* :func:`check_run_dir` — a new run refuses a directory holding a checkpoint or results unless ``overwrite=true``,
  which removes every output of the earlier run (:func:`clear_run_outputs`).
* :class:`RunDirGuard` — the recipes' Hydra callback: the config, the run directory and a resume are checked (and the
  directory claimed) before Hydra writes its ``.hydra/`` record, so a refused command changes nothing on disk.
* :func:`read_checkpoint` / :func:`check_resume_config` — a checkpoint is read with ``torch.load(weights_only=True)``
  (reading it never runs code); a corrupted checkpoint, or a file that is not one, is a clear error naming the file;
  a resumed config may differ from the checkpoint's only in :data:`CONTINUABLE_KEYS`, and ``q.steps`` may only
  grow (never below the steps already trained).
* :class:`TrainingDiverged` / :func:`first_non_finite` — a non-finite loss, Q or ratio stops the run, naming the
  stage, the step and the figure.
* :class:`StopSignals` — SIGINT and SIGTERM end the run at the next step boundary, after a checkpoint.
* :func:`json_safe` — NaN and ±inf become ``null``, so ``results.json`` stays valid JSON.
* :func:`atomic_write` — checkpoints and JSON files are written to a temporary file, fsynced and renamed over the
  old one: a run killed at any point (SIGKILL included) leaves no half-written file.
"""
from __future__ import annotations

import contextlib
import errno
import math
import os
import pickle
import shutil
import signal
import threading
import zipfile
from pathlib import Path

import torch
from hydra.experimental.callback import Callback

try:  # advisory locks (POSIX); without them a run directory is not locked
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

from torchrl_wbrm.data.tasks import get_task
from torchrl_wbrm.keys import CHECKPOINT

__all__ = [
    "CONTINUABLE_KEYS",
    "CONTINUABLE_PREFIXES",
    "RunDirClaim",
    "RunDirGuard",
    "RunDirInUse",
    "RunInterrupted",
    "StopSignals",
    "TrainingDiverged",
    "changed_keys",
    "check_resume_config",
    "check_run_dir",
    "claim_run_dir",
    "clear_run_outputs",
    "first_non_finite",
    "json_safe",
    "non_finite_parameter",
    "read_checkpoint",
]

#: Files that mark a directory as holding a run.
RUN_FILES = (CHECKPOINT, "results.json")
#: Keys a resumed run may change: they do not change what has been trained (``q.steps`` only upwards).
CONTINUABLE_KEYS = (
    "q.steps",
    "q.eval_every",
    "checkpoint_every",
    "resume",
    "overwrite",
    "plots",
    "threads",
    "data_cache",
)
#: Whole sections a resumed run may change: evaluation and logging settings.
CONTINUABLE_PREFIXES = ("eval.", "logger.")
#: Keys of a checkpoint written by :meth:`WBRMTrainer.state_dict`.
CHECKPOINT_KEYS = ("state", "history", "rng", "q_loss", "config", "data_fingerprint")


class TrainingDiverged(RuntimeError):
    """A non-finite figure or parameter stopped the run; ``stage``, ``step``, ``figure`` and ``value`` say where."""

    def __init__(self, stage: str, step: int, figure: str, value: float, checkpoint_step: int | None = None):
        self.stage, self.step, self.figure, self.value = stage, step, figure, value
        self.checkpoint_step = checkpoint_step
        super().__init__(
            f"Training diverged in stage {stage!r} at step {step}: {figure} = {value}. The run stopped; the last "
            f"checkpoint with finite values is kept."
        )


#: the command the resume hint of :class:`RunInterrupted` starts with (the entry point sets how it was started)
RESUME_COMMAND = "python recipes/wbrm_offline.py"


class RunInterrupted(Exception):
    """SIGINT or SIGTERM stopped the run after a checkpoint; ``signal_name``, ``stage``, ``step``, ``run_dir``."""

    def __init__(self, signum: int, stage: str, step: int, run_dir: Path, *, during: str | None = None):
        self.signum, self.stage, self.step, self.run_dir = signum, stage, step, Path(run_dir)
        self.signal_name = signal.Signals(signum).name
        self.during = during
        where = f"during the {during} " if during else ""
        super().__init__(
            f"{self.signal_name} received: stopped {where}in stage {stage!r} at step {step}, checkpoint written to "
            f"{self.run_dir / CHECKPOINT}. Resume with: {RESUME_COMMAND} resume={self.run_dir}"
        )

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


class StopNow(Exception):
    """A signal interrupted a :meth:`StopSignals.immediately` block; ``signum`` is the signal."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(f"{signal.Signals(signum).name} received")


class StopSignals:
    """A context manager that turns SIGINT/SIGTERM into a flag (``.received``: the signal number or ``None``).

    The trainer polls it at step boundaries, writes a checkpoint and raises :class:`RunInterrupted`. A second signal
    while the flag is set falls back to the previous handler (so a stuck run can still be killed). Off the main
    thread (where Python cannot install handlers) it does nothing.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.received: int | None = None
        self._previous: dict = {}
        self._immediate = False

    def _handle(self, signum, frame) -> None:
        if self.received is not None:  # a second signal: the previous behaviour (KeyboardInterrupt, or exit)
            previous = self._previous.get(signum)
            if callable(previous):
                previous(signum, frame)
            else:
                raise KeyboardInterrupt
            return
        self.received = signum
        if self._immediate:  # inside immediately(): stop now, not at the next step boundary
            self._immediate = False
            raise StopNow(signum)

    @contextlib.contextmanager
    def immediately(self):
        """A block a signal interrupts at once (:class:`StopNow`), for work that can be abandoned and redone, such as
        an evaluation (it changes no training state): a long evaluation stops promptly instead of looking hung. A
        signal received before the block raises at its start."""
        if self.received is not None:
            raise StopNow(self.received)
        self._immediate = True
        try:
            yield
        finally:
            self._immediate = False

    def __enter__(self) -> "StopSignals":
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                self._previous[sig] = signal.getsignal(sig)
                signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous if previous is not None else signal.SIG_DFL)
        self._previous = {}


#: What a run writes into its directory (besides Hydra's record): removed by ``overwrite=true`` so that no output of
#: the earlier run (its CSV logs above all, which torchrl's ``CSVLogger`` would append to) outlives it.
RUN_OUTPUTS = (CHECKPOINT, "checkpoint.tmp", "results.json", "results.json.tmp", "history.json", "history.json.tmp",
               "training_curve.png", "evaluation.png", "logs", "wandb")
#: Hydra's record of the command that made the run (``.hydra/``) and its job log (``<job name>.log``).
HYDRA_RECORD = (".hydra",)


def holds_run(run_dir: Path) -> list[str]:
    """The files of :data:`RUN_FILES` (and ``history.json``) in ``run_dir``, if any of :data:`RUN_FILES` is there."""
    present = [name for name in (*RUN_FILES, "history.json") if (Path(run_dir) / name).exists()]
    return present if any(name in RUN_FILES for name in present) else []


def clear_run_outputs(run_dir: Path, *, hydra_record: bool = False) -> list[str]:
    """Remove the earlier run's outputs from ``run_dir`` (:data:`RUN_OUTPUTS`; with ``hydra_record`` also its
    ``.hydra/`` record and Hydra job logs ``*.log``); other files are left alone. Returns what was removed."""
    run_dir = Path(run_dir)
    names = list(RUN_OUTPUTS)
    if hydra_record:
        names += [*HYDRA_RECORD, *(p.name for p in run_dir.glob("*.log") if p.is_file())]
    removed = []
    for name in names:
        path = run_dir / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.exists() or path.is_symlink():
            path.unlink()
        else:
            continue
        removed.append(name)
    return removed


def check_run_dir(run_dir: Path, *, overwrite: bool, remove: bool = True) -> None:
    """Refuse a new run into a directory that already holds a run, unless ``overwrite`` (then, with ``remove``,
    every output of the earlier run is removed: :func:`clear_run_outputs`)."""
    present = holds_run(run_dir)
    if not present:
        return
    if not overwrite:
        raise FileExistsError(
            f"{run_dir} already holds a run ({', '.join(present)}). Continue it with resume={run_dir}, choose another "
            f"directory, or pass overwrite=true to replace it."
        )
    if remove:
        clear_run_outputs(run_dir)


class RunDirInUse(RuntimeError):
    """Another run holds the run directory (:func:`claim_run_dir`)."""


class RunDirClaim:
    """An exclusive claim on a run directory: ``fcntl.flock`` on the directory's own file descriptor.

    Nothing is written for it, and the kernel drops it when the process ends, so a killed run leaves no stale lock.
    Released by :meth:`release` (or when this object is collected).
    """

    def __init__(self, path: Path, fd: int | None) -> None:
        self.path, self._fd = Path(path), fd

    @property
    def held(self) -> bool:
        return self._fd is not None

    def release(self) -> None:
        fd, self._fd = self._fd, None
        if fd is not None and fd >= 0:
            os.close(fd)  # closing the descriptor drops its lock

    def __del__(self) -> None:
        self.release()

    def __repr__(self) -> str:
        return f"RunDirClaim({str(self.path)!r}, held={self.held})"


def claim_run_dir(run_dir: str | os.PathLike) -> RunDirClaim:
    """Claim the existing directory ``run_dir`` for one run, or raise :class:`RunDirInUse` if another run (in this
    process or another) holds it. Two runs can then never write one directory: the claim is taken before the
    directory is checked for an earlier run and held until the run ends."""
    path = Path(run_dir)
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    if fcntl is None:  # pragma: no cover - no advisory locks on this platform
        os.close(fd)
        return RunDirClaim(path, -1)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as err:
        os.close(fd)
        if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            raise RunDirInUse(
                f"{path} is in use by another run (it holds the directory's lock until it ends). Wait for that run "
                f"to end, or choose another directory (hydra.run.dir=...)."
            ) from err
        return RunDirClaim(path, -1)  # a file system without flock: unlocked, as before
    return RunDirClaim(path, fd)


#: Claims taken before a run's trainer exists (by :class:`RunDirGuard`), handed to it by :func:`take_claim`.
_HANDED_OVER: dict[str, RunDirClaim] = {}


def hand_over(claim: RunDirClaim) -> None:
    """Keep ``claim`` for the trainer of the same run directory in this process (:func:`take_claim`)."""
    _HANDED_OVER[os.path.realpath(claim.path)] = claim


def take_claim(run_dir: str | os.PathLike) -> RunDirClaim | None:
    """The claim :func:`hand_over` kept for ``run_dir`` (once), or ``None``."""
    claim = _HANDED_OVER.pop(os.path.realpath(run_dir), None)
    return claim if claim is not None and claim.held else None


def _numpy_array_globals() -> list:
    """NumPy's array reconstruction, allowed to :func:`read_checkpoint`'s restricted unpickler for the one thing a
    checkpoint of an older version holds beyond tensors and primitives: NumPy's random state (an ``uint32`` array).
    These build an array from its bytes and dtype; nothing they touch runs code."""
    import numpy as np

    multiarray = getattr(np, "_core", None) or np.core
    return [multiarray.multiarray._reconstruct, np.ndarray, np.dtype, type(np.dtype(np.uint32))]


def _pickle_globals(path: Path) -> list[str]:
    """The globals (``module.name``) a pickle file would import when read, listed from its opcodes without running
    any (``torch.save``'s zip archive, or a bare pickle); ``[]`` when they cannot be listed."""
    import pickletools

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
    import pickletools
    import re

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
    import warnings

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
    return sd


def check_run_record(record: Path, overrides: list[str]) -> None:
    """Refuse a run's Hydra record (``.hydra/overrides.yaml``, re-applied by ``resume=``) holding an override that is
    not a setting of the recipe's own config (:class:`~torchrl_wbrm.training.config.WBRMConfig`): a record Hydra wrote
    holds only those (``env=lqr_exp3``, ``q.lr=0.003``; Hydra's own settings go to ``hydra.yaml``). Anything else,
    such as a ``hydra.callbacks`` entry whose ``_target_`` Hydra would import and call, is refused before Hydra sees
    it: a resume never runs what a file in the run directory names."""
    from dataclasses import fields

    from torchrl_wbrm.training.config import WBRMConfig

    settings = {f.name for f in fields(WBRMConfig)}
    for override in overrides:
        key = override.split("=", 1)[0].lstrip("+~")
        if "=" not in override or key.split(".", 1)[0].split("/", 1)[0] not in settings:
            raise ValueError(
                f"Cannot resume: {record} holds the override {override!r}, which is not a setting of this recipe "
                f"(a run's record holds only its own settings, such as env=lqr_exp3 or q.lr=0.003); nothing in it was "
                f"applied."
            )


def _flatten(node, prefix: str = "") -> dict:
    if isinstance(node, dict):
        out = {}
        for k, v in node.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: node}


def changed_keys(old: dict, new: dict) -> dict[str, tuple]:
    """Dotted key -> ``(old, new)`` for every leaf that differs between two nested config dicts."""
    a, b = _flatten(old), _flatten(new)
    missing = object()
    out = {}
    for key in sorted(set(a) | set(b)):
        va, vb = a.get(key, missing), b.get(key, missing)
        if va != vb:
            out[key] = (None if va is missing else va, None if vb is missing else vb)
    return out


def is_continuable(key: str) -> bool:
    return key in CONTINUABLE_KEYS or key.startswith(CONTINUABLE_PREFIXES)


#: Keys a finished run's results may be reused under when they differ: the continuable ones that change no figure a
#: finished run reports (not the step budget, the evaluation schedule or the evaluation settings).
REUSABLE_KEYS = tuple(k for k in CONTINUABLE_KEYS if not k.startswith("q."))
REUSABLE_PREFIXES = ("logger.",)


def _describe(changes: dict[str, tuple]) -> str:
    return "; ".join(f"{k}: {old!r} -> {new!r}" for k, (old, new) in changes.items())


def check_finished_config(path: Path, saved: dict, now: dict) -> None:
    """Refuse to reuse a finished run's results (``path``) for a config that differs from the one it ran with, outside
    :data:`REUSABLE_KEYS` (the logger, plots, threads and where the data are cached): every such key is named with its
    old and new value. A study that skips its finished runs would otherwise report them as this config's."""
    refused = {k: v for k, v in changed_keys(saved, now).items()
               if k not in REUSABLE_KEYS and not k.startswith(REUSABLE_PREFIXES)}
    if refused:
        raise ValueError(
            f"{path} holds a finished run with other settings: {_describe(refused)}. Its results are not this config's; write "
            f"this config's runs to another directory (a study's --out), or delete that run to redo it."
        )


def check_resume_config(path: Path, saved: dict, now: dict, state: dict) -> dict[str, tuple]:
    """Refuse a resume whose config differs from the checkpoint's outside :data:`CONTINUABLE_KEYS` (every such key
    named with its old and new value), or whose ``q.steps`` is below the steps already trained. Returns the
    (continuable) changes."""
    changes = changed_keys(saved, now)
    refused = {k: v for k, v in changes.items() if not is_continuable(k)}
    if "q.steps" in changes and now.get("q", {}).get("lr_schedule", "constant") != "constant":
        refused["q.steps"] = changes["q.steps"]  # the schedule's horizon is the step budget
    if refused:
        raise ValueError(
            f"Cannot resume from {path}: these settings differ from the checkpoint's and cannot change in a resumed "
            f"run: {_describe(refused)}. Only {', '.join(CONTINUABLE_KEYS)} (q.steps upwards, and not with an lr schedule) and "
            f"the {', '.join(p.rstrip('.') for p in CONTINUABLE_PREFIXES)} settings may change; start a new run for "
            f"anything else."
        )
    trained = state.get("step", 0) if state.get("stage") in ("q", "done") else 0
    steps = now.get("q", {}).get("steps")
    if steps is not None and steps < trained:
        raise ValueError(
            f"Cannot resume from {path}: q.steps={steps} is smaller than the {trained} steps already trained "
            f"(a resumed run can only continue; start a new run for a smaller budget)."
        )
    return changes


def first_non_finite(figures: dict) -> tuple[str, float] | None:
    """The first ``(name, value)`` among scalar tensors/floats of ``figures`` that is NaN or ±inf (one host sync)."""
    names, values = [], []
    for name, value in figures.items():
        if isinstance(value, torch.Tensor):
            if value.numel() == 1:
                names.append(name)
                values.append(value.detach().reshape(()).to(torch.float64, copy=False))
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            names.append(name)
            values.append(torch.tensor(float(value), dtype=torch.float64))
    if not values:
        return None
    stacked = torch.stack([v.cpu() for v in values])
    finite = torch.isfinite(stacked)
    if bool(finite.all()):
        return None
    i = int((~finite).nonzero()[0])
    return names[i], float(stacked[i])


def non_finite_parameter(*modules) -> str | None:
    """The name of the first parameter or buffer with a non-finite entry in ``modules``, or ``None``."""
    for module in modules:
        if module is None:
            continue
        for name, tensor in (*module.named_parameters(), *module.named_buffers()):
            if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
                return name
    return None


def json_safe(obj):
    """``obj`` with NaN and ±inf replaced by ``None`` (valid JSON), tensors and numpy scalars as numbers."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, torch.Tensor) and obj.numel() == 1:
        obj = obj.item()
    if hasattr(obj, "item") and callable(obj.item) and not isinstance(obj, (str, bytes)):
        try:
            obj = obj.item()
        except (TypeError, ValueError):
            pass
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


#: The test hook's environment variable (:func:`pause_for_test`); outside tests it is unset and the hook does nothing.
TEST_PAUSE_ENV = "TORCHRL_WBRM_TEST_PAUSE_AT"
#: How many times this process has replaced each file name (:func:`atomic_write`), for the hook's ``<name>:<n>``.
_REPLACED: dict[str, int] = {}


def pause_for_test(point: str) -> None:
    """Test hook for kill tests: when the environment variable :data:`TEST_PAUSE_ENV` equals ``point``, print
    ``TORCHRL_WBRM_TEST_PAUSE_AT: paused at <point>`` on stderr and wait (for the test to kill the process).

    Points: ``<stage>:<step>`` after a training step (``ratio:15``, ``q:25``), and ``<file name>:<n>`` inside the
    n-th :func:`atomic_write` of that file in this process, after the new content is on disk in the temporary file and
    before it replaces the file (``checkpoint.pt:4``, ``results.json:1``). Unset, the hook does nothing."""
    if os.environ.get(TEST_PAUSE_ENV) != point:
        return
    import sys
    import time

    print(f"{TEST_PAUSE_ENV}: paused at {point}", file=sys.stderr, flush=True)
    while True:
        time.sleep(60)


def _fsync_dir(directory: Path) -> None:
    """Make a rename in ``directory`` durable (where the platform lets a directory be opened and synced)."""
    try:
        fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write(path: Path, write, *, tmp: Path | None = None) -> None:
    """Replace ``path`` with what ``write(file)`` writes, atomically: the content goes to ``tmp`` (default
    ``<path>.tmp``, in the same directory), is flushed and fsynced, then renamed over ``path`` (``os.replace``) and
    the directory synced. A process killed at any point leaves either the old ``path`` or the new one complete, never
    a half-written one (at most a stale temporary file, which the next write replaces)."""
    path = Path(path)
    tmp = Path(tmp) if tmp is not None else path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        write(f)
        f.flush()
        os.fsync(f.fileno())
    _REPLACED[path.name] = _REPLACED.get(path.name, 0) + 1
    pause_for_test(f"{path.name}:{_REPLACED[path.name]}")
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def write_json(path: Path, obj) -> None:
    """Write ``obj`` as strict JSON (``allow_nan=False`` after :func:`json_safe`), atomically (:func:`atomic_write`)."""
    import json

    text = json.dumps(json_safe(obj), indent=2, default=float, allow_nan=False)
    atomic_write(path, lambda f: f.write(text.encode()))


def _leaves(node, prefix: str = ""):
    from dataclasses import fields, is_dataclass

    if is_dataclass(node):
        for f in fields(node):
            yield from _leaves(getattr(node, f.name), f"{prefix}{f.name}.")
    elif isinstance(node, (list, tuple)):
        for i, v in enumerate(node):
            yield from _leaves(v, f"{prefix[:-1]}[{i}].")
    else:
        yield prefix[:-1], node


def check_device(device: str, key: str = "device") -> None:
    """Refuse a device string torch cannot parse or whose backend is not available here, naming ``key``."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as err:
        raise ValueError(f"{key}={device!r} is not a torch device ({err}); use e.g. cpu or cuda.") from err
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"{key}={device!r} but CUDA is not available on this machine (torch.cuda.is_available() "
                             f"is False); use {key}=cpu.")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"{key}={device!r} but this machine has {torch.cuda.device_count()} CUDA device(s).")
    elif dev.type == "mps":
        if not (getattr(torch.backends, "mps", None) and torch.backends.mps.is_available()):
            raise ValueError(f"{key}={device!r} but MPS is not available on this machine; use {key}=cpu.")
    elif dev.type != "cpu":
        raise ValueError(f"{key}={device!r}: only cpu, cuda and mps devices are supported.")


def check_logger(logger_cfg, key: str = "logger") -> None:
    """Refuse, before any data are collected, a wandb setting wandb itself would refuse when the run starts: the
    project name (checked by ``wandb.Settings``, so the rule is wandb's own: no ``/ \\ # ? % :``, at most 128
    characters) and the group."""
    if getattr(logger_cfg, "backend", None) != "wandb":
        return
    try:
        import wandb
    except ImportError as err:
        raise ValueError(f"{key}.backend='wandb' needs the wandb package (pip install wandb), which is not "
                         f"installed.") from err
    for name in ("project", "group"):
        value = getattr(logger_cfg, name, None)
        if value is None:
            continue
        try:
            wandb.Settings(**{"run_group" if name == "group" else name: str(value)})
        except Exception as err:  # noqa: BLE001 (wandb's UsageError or pydantic's ValidationError)
            raise ValueError(f"{key}.{name}={value!r} is refused by wandb: {err}") from err


def validate_run_settings(cfg) -> None:
    """The checks :func:`~torchrl_wbrm.training.config.validate_config` adds for the run as a whole, all before any
    data are collected: finite numbers, seeds, sizes, threads, the device, and what the exact LQR return supports."""
    for key, value in _leaves(cfg):
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"{key}={value!r}: every number in the config must be finite.")
    if not cfg.seed >= 0:
        raise ValueError(f"seed must be >= 0, got {cfg.seed!r}.")
    if not cfg.eval.seed >= 0:
        raise ValueError(f"eval.seed must be >= 0, got {cfg.eval.seed!r}.")
    if not cfg.eval.q_samples > 0:
        raise ValueError(f"eval.q_samples must be > 0 (the samples of the Q* and ratio errors), got {cfg.eval.q_samples!r}.")
    if cfg.threads is not None and not cfg.threads >= 1:
        raise ValueError(f"threads must be >= 1 or null (torch's default), got {cfg.threads!r}.")
    if not cfg.checkpoint_every >= 0:
        raise ValueError(f"checkpoint_every must be >= 0 (0: only at the end of each stage), got {cfg.checkpoint_every!r}.")
    if not cfg.ratio.patience >= 1:
        raise ValueError(f"ratio.patience must be >= 1, got {cfg.ratio.patience!r}.")
    if cfg.q.maximiser == "sampled" and not cfg.q.num_action_samples >= 1:
        raise ValueError(f"q.num_action_samples must be >= 1, got {cfg.q.num_action_samples!r}.")
    check_device(cfg.device)
    check_logger(cfg.logger)
    get_task(cfg.env).validate()  # the env's data settings, and what its ground truth supports


def _task_config(config):
    """The run's own config (without the ``hydra`` node) as a :class:`~torchrl_wbrm.training.config.WBRMConfig`."""
    from omegaconf import OmegaConf

    task = OmegaConf.masked_copy(config, [k for k in config.keys() if k != "hydra"])
    return OmegaConf.to_object(OmegaConf.merge(_schema(), task))


def _schema():
    from omegaconf import OmegaConf

    from torchrl_wbrm.training.config import WBRMConfig

    return OmegaConf.structured(WBRMConfig)


def _set_run_dir(config, run_dir: Path) -> None:
    from omegaconf import open_dict, read_write

    with read_write(config.hydra), open_dict(config.hydra):
        config.hydra.run.dir = str(run_dir)


def _unique_dir(path: Path) -> Path:
    """Create ``path`` (or ``path_1``, ``path_2``, ... if it exists) with one exclusive ``mkdir`` each: two runs that
    start in the same second get directories of their own."""
    path.parent.mkdir(parents=True, exist_ok=True)
    for i in range(1000):
        candidate = path if i == 0 else path.with_name(f"{path.name}_{i}")
        try:
            candidate.mkdir()
            return candidate
        except FileExistsError:
            continue
    raise FileExistsError(f"Could not create a fresh run directory next to {path} (1,000 of them exist).")


def check_run_request(cfg, run_dir: Path, *, resume: bool,
                      claim: RunDirClaim | None = None) -> tuple[RunDirClaim, dict | None]:
    """Everything that can refuse a run in ``run_dir`` before it starts, with nothing written: the directory is
    claimed (:func:`claim_run_dir`, unless ``claim`` is this run's already), then a resume's checkpoint is read and
    its config compared (:func:`check_resume_config`), or a new run's directory checked for an earlier run
    (:func:`check_run_dir`, nothing removed yet). Returns the claim (released again if the run is refused) and the
    checkpoint read (``None`` for a new run)."""
    from torchrl_wbrm.training.trainer import config_as_dict

    run_dir = Path(run_dir)
    path = run_dir / CHECKPOINT
    if resume and not path.is_file():
        read_checkpoint(path)  # FileNotFoundError naming the directory; nothing is created
    claim = claim or claim_run_dir(run_dir)
    sd = None
    try:
        if resume:
            sd = read_checkpoint(path)
            check_resume_config(path, dict(sd["config"]), config_as_dict(cfg), sd["state"])
        else:
            check_run_dir(run_dir, overwrite=cfg.overwrite, remove=False)
    except BaseException:
        claim.release()
        raise
    return claim, sd


class RunDirGuard(Callback):
    """The recipes' Hydra callback (``hydra.callbacks.run_dir_guard``): a run request is checked before Hydra writes
    anything, so a refused command leaves the disk as it was (no ``.hydra/`` record rewritten, no empty dated
    directory under ``outputs/``).

    In ``on_run_start`` (before Hydra creates the run directory and writes ``.hydra/``):

    * the config is validated (:func:`~torchrl_wbrm.training.config.validate_config`);
    * the data on disk it names are read and checked (:meth:`~torchrl_wbrm.data.tasks.Task.check_data`: a Minari
      pair, or a saved dataset), and held for the run's trainer, which does not read them again;
    * ``resume=X``: Hydra's run directory becomes ``X`` (its record goes with the run it continues), ``X`` must hold
      a checkpoint whose config this one may continue, and ``X`` is claimed;
    * a new run: the default dated directory is created with an exclusive ``mkdir`` (``_1``, ``_2``, ... when two
      runs start in the same second), a given ``hydra.run.dir`` is claimed and must not hold a run unless
      ``overwrite=true``, which then removes the earlier run's outputs and its Hydra record.

    The claim is handed to the run's :class:`~torchrl_wbrm.training.WBRMTrainer` (:func:`take_claim`), which holds it
    until the run ends. A refusal exits (``SystemExit``, status 1) with the reason in one line, and with the
    traceback before it only under ``verbose=true``; Hydra would only warn about an exception raised by a callback.
    """

    def on_run_start(self, config, **kwargs) -> None:
        from omegaconf.errors import OmegaConfBaseException

        try:
            self.check(config)
        except (ValueError, TypeError, KeyError, OSError, RuntimeError, OmegaConfBaseException) as err:
            if _verbose(config):
                import traceback

                traceback.print_exc()
            reason = " ".join(str(err).split()) or type(err).__name__  # one line
            raise SystemExit(f"Refused (nothing was written): {reason}") from err

    @staticmethod
    def check(config) -> RunDirClaim:
        """The checks of :meth:`on_run_start` on a composed config (with its ``hydra`` node); returns the claim."""
        from omegaconf import OmegaConf

        from torchrl_wbrm.training.config import validate_config

        cfg = _task_config(config)
        validate_config(cfg)
        get_task(cfg.env).check_data()  # bad data are refused here, before anything is written
        raw_dir = OmegaConf.to_container(config.hydra.run, resolve=False)["dir"]
        dated = isinstance(raw_dir, str) and "${now:" in raw_dir
        if cfg.resume:
            run_dir = Path(cfg.resume)
            given = Path(str(config.hydra.run.dir))
            if not dated and given.resolve() != run_dir.resolve():
                raise ValueError(
                    f"resume={cfg.resume} continues the run in {run_dir}, but hydra.run.dir={given} would put this "
                    f"command's Hydra record elsewhere; drop hydra.run.dir (a resume runs in its own directory)."
                )
            claim, _ = check_run_request(cfg, run_dir, resume=True)
        else:
            run_dir = Path(str(config.hydra.run.dir))
            if dated:  # a fresh directory of its own, even for two runs started in the same second
                run_dir = _unique_dir(run_dir)
                claim = claim_run_dir(run_dir)
            else:
                created = not run_dir.exists()
                run_dir.mkdir(parents=True, exist_ok=True)
                try:
                    claim, _ = check_run_request(cfg, run_dir, resume=False)
                except BaseException:
                    if created:
                        _remove_empty(run_dir)
                    raise
                if cfg.overwrite and holds_run(run_dir):  # the earlier run goes, record and logs too
                    clear_run_outputs(run_dir, hydra_record=True)
        _set_run_dir(config, run_dir)
        hand_over(claim)
        return claim


def _verbose(config) -> bool:
    """The composed config's ``verbose`` setting (``False`` where it cannot be read)."""
    from omegaconf import OmegaConf

    try:
        return OmegaConf.select(config, "verbose", default=False) is True
    except Exception:  # noqa: BLE001 (a config too broken to read: no traceback)
        return False


def _remove_empty(path: Path) -> None:
    try:
        path.rmdir()
    except OSError:
        pass
