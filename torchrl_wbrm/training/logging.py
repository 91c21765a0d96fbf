"""Loggers through ``torchrl.record.loggers.get_logger``: CSV by default, wandb offline unless asked otherwise."""
from __future__ import annotations

import os
from pathlib import Path

from torchrl.record.loggers import get_logger

__all__ = ["make_logger"]


def make_logger(logger_cfg, run_dir: str | os.PathLike, experiment_name: str, config: dict | None = None):
    """A torchrl ``Logger`` writing under ``run_dir`` (``None`` when ``logger_cfg.backend`` is empty).

    wandb runs ``offline`` unless ``logger_cfg.mode`` says ``"online"`` (this project assumes no network and no API
    key); the run's config is recorded with ``log_hparams`` so it shows on the dashboard.
    """
    backend = logger_cfg.backend
    run_dir = Path(run_dir)
    if backend == "":
        return None
    if backend == "csv":
        logger = get_logger("csv", logger_name=str(run_dir / "logs"), experiment_name=experiment_name)
    elif backend == "wandb":
        os.environ.setdefault("WANDB_SILENT", "true")
        kwargs = {"project": logger_cfg.project, "config": config or {}}
        if logger_cfg.mode == "offline":
            kwargs["offline"] = True
        else:
            kwargs["mode"] = logger_cfg.mode
        logger = get_logger("wandb", logger_name=str(run_dir), experiment_name=experiment_name, wandb_kwargs=kwargs)
    else:
        raise ValueError(f"logger.backend must be 'csv', 'wandb' or '' (none), got {backend!r}.")
    if config is not None and backend == "csv":
        logger.log_hparams(config)
    return logger
