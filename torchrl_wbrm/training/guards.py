"""What keeps a run honest: safe run directories, resume checks, divergence detection, signals, strict JSON.

* :func:`check_run_dir` — a new run refuses a directory holding a checkpoint or results unless ``overwrite=true``.
* :func:`read_checkpoint` / :func:`check_resume_config` — a corrupted checkpoint is a clear error naming the file;
  a resumed config may differ from the checkpoint's only in :data:`CONTINUABLE_KEYS`, and ``q.steps`` may only
  grow (never below the steps already trained).
* :class:`TrainingDiverged` / :func:`first_non_finite` — a non-finite loss, Q or ratio stops the run, naming the
  stage, the step and the figure.
* :class:`StopSignals` — SIGINT and SIGTERM end the run at the next step boundary, after a checkpoint.
* :func:`json_safe` — NaN and ±inf become ``null``, so ``results.json`` stays valid JSON.
"""
from __future__ import annotations

import math
import os
import pickle
import signal
import threading
import zipfile
from pathlib import Path

import torch

from torchrl_wbrm.data.tasks import get_task

__all__ = [
    "CONTINUABLE_KEYS",
    "CONTINUABLE_PREFIXES",
    "RunInterrupted",
    "StopSignals",
    "TrainingDiverged",
    "changed_keys",
    "check_resume_config",
    "check_run_dir",
    "first_non_finite",
    "json_safe",
    "non_finite_parameter",
    "read_checkpoint",
]

CHECKPOINT = "checkpoint.pt"
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


class RunInterrupted(Exception):
    """SIGINT or SIGTERM stopped the run after a checkpoint; ``signal_name``, ``stage``, ``step``, ``run_dir``."""

    def __init__(self, signum: int, stage: str, step: int, run_dir: Path):
        self.signum, self.stage, self.step, self.run_dir = signum, stage, step, Path(run_dir)
        self.signal_name = signal.Signals(signum).name
        super().__init__(
            f"{self.signal_name} received: stopped in stage {stage!r} at step {step}, checkpoint written to "
            f"{self.run_dir / CHECKPOINT}. Resume with: python recipes/wbrm_offline.py resume={self.run_dir}"
        )

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


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

    def _handle(self, signum, frame) -> None:
        if self.received is not None:  # a second signal: the previous behaviour (KeyboardInterrupt, or exit)
            previous = self._previous.get(signum)
            if callable(previous):
                previous(signum, frame)
            else:
                raise KeyboardInterrupt
            return
        self.received = signum

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


def check_run_dir(run_dir: Path, *, overwrite: bool) -> None:
    """Refuse a new run into a directory that already holds a run (unless ``overwrite``, which removes those files)."""
    present = [name for name in (*RUN_FILES, "history.json") if (Path(run_dir) / name).exists()]
    if not present or not any(name in RUN_FILES for name in present):
        return
    if not overwrite:
        raise FileExistsError(
            f"{run_dir} already holds a run ({', '.join(present)}). Continue it with resume={run_dir}, choose another "
            f"directory, or pass overwrite=true to replace it."
        )
    for name in present:
        (Path(run_dir) / name).unlink()


def read_checkpoint(path: Path) -> dict:
    """``torch.load`` of a checkpoint, or a ``RuntimeError`` naming the file if it is damaged or not a checkpoint."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Cannot resume: no {path.name} in {path.parent}.")
    try:
        sd = torch.load(path, weights_only=False, map_location="cpu")
    except (pickle.UnpicklingError, EOFError, RuntimeError, zipfile.BadZipFile, ValueError, KeyError,
            AttributeError, ImportError, IndexError, TypeError, UnicodeDecodeError, OSError) as err:
        raise RuntimeError(
            f"Cannot resume: {path} is corrupted or not a checkpoint ({type(err).__name__}: {err}). Start a new run "
            f"in another directory, or pass overwrite=true to replace this one."
        ) from err
    missing = [k for k in CHECKPOINT_KEYS if not isinstance(sd, dict) or k not in sd]
    if missing:
        raise RuntimeError(f"Cannot resume: {path} is not a complete checkpoint (it lacks {missing}).")
    return sd


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


def write_json(path: Path, obj) -> None:
    """Write ``obj`` as strict JSON (``allow_nan=False`` after :func:`json_safe`), atomically."""
    import json

    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(json_safe(obj), indent=2, default=float, allow_nan=False))
    os.replace(tmp, path)


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
    get_task(cfg.env).validate()  # the env's data settings, and what its ground truth supports
