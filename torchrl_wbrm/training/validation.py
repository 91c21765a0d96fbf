"""The checks of a run's settings as a whole that a type cannot make, all before any data are collected: finite
numbers, seeds, sizes, threads, the device and the logger (:func:`validate_run_settings`, called by
:func:`~torchrl_wbrm.training.config.validate_config`; which check goes where: :mod:`torchrl_wbrm.training.config`).
"""
from __future__ import annotations

import math
import os
from dataclasses import fields, is_dataclass

import torch

__all__ = ["SEED_LIMIT", "check_device", "check_logger", "check_seeds", "check_writable_folder",
           "validate_run_settings"]


def _leaves(node, prefix: str = ""):
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


#: Seeds lie in ``[0, 2**32)``: NumPy's and the envs' seeds are 32-bit, so a larger seed would repeat the draws of
#: the seed it equals mod ``2**32``.
SEED_LIMIT = 2**32


def check_seeds(cfg) -> None:
    """Refuse, naming the setting, a seed (``seed``, ``eval.seed``, an entry of ``seeds``) outside ``[0, 2**32)``,
    and ``seeds`` holding two seeds the random generators would take as one (equal mod ``2**32``): those runs would
    be the same run counted twice."""
    for key, value in (("seed", cfg.seed), ("eval.seed", cfg.eval.seed)):
        if not value >= 0:
            raise ValueError(f"{key} must be >= 0, got {value!r}.")
        if not (isinstance(value, int) and 0 <= value < SEED_LIMIT):
            raise ValueError(f"{key}={value!r} is out of range: a seed must be an integer in [0, 2**32 - 1] "
                             f"(NumPy's and the envs' seeds are 32-bit; a larger one repeats a smaller one's draws).")
    if cfg.seeds is None:
        return
    seen: dict[int, int] = {}
    for seed in cfg.seeds:
        if not (isinstance(seed, int) and 0 <= seed < SEED_LIMIT):
            raise ValueError(f"seeds holds {seed!r}, out of range: a seed must be an integer in [0, 2**32 - 1] "
                             f"(NumPy's and the envs' seeds are 32-bit; {seed!r} would repeat the draws of seed "
                             f"{seed % SEED_LIMIT if isinstance(seed, int) else '?'}).")
        if seed in seen:
            raise ValueError(f"seeds={list(cfg.seeds)} holds seed {seed} twice: each seed is one run.")
        seen[seed] = seed


def check_writable_folder(path, key: str) -> None:
    """Refuse, naming ``key``, a folder a run writes into that cannot be written: the folder itself if it exists,
    else the nearest existing folder above it (read-only file system, permissions)."""
    from pathlib import Path

    folder = Path(path).absolute()
    probe = folder
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        raise ValueError(f"{key}={path}: {probe} is not a folder.")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise ValueError(f"{key}={path}: {probe} cannot be written (a read-only file system or its permissions); choose "
                         f"a folder this user can write.")
    statvfs = getattr(os, "statvfs", None)
    if statvfs is not None:
        try:
            read_only = bool(statvfs(probe).f_flag & getattr(os, "ST_RDONLY", 1))
        except OSError:
            read_only = False
        if read_only:
            raise ValueError(f"{key}={path}: {probe} lies on a read-only file system; choose a folder this user can "
                             f"write.")


def validate_run_settings(cfg) -> None:
    """The checks :func:`~torchrl_wbrm.training.config.validate_config` adds for the run as a whole, all before any
    data are collected: finite numbers, seeds, sizes, threads, the device and the logger."""
    for key, value in _leaves(cfg):
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"{key}={value!r}: every number in the config must be finite.")
    check_seeds(cfg)
    if not cfg.eval.q_samples >= 2:
        raise ValueError(f"eval.q_samples must be >= 2 (the samples of the Q* and ratio errors, which are relative to "
                         f"Q*'s spread over them: one sample has none), got {cfg.eval.q_samples!r}.")
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
    if cfg.data_cache:
        check_writable_folder(cfg.data_cache, "data_cache")
