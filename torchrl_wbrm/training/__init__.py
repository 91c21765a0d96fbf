"""The two-stage trainer, structured configs, logging, checkpoints and plots (used by every recipe)."""
from torchrl_wbrm.training.config import (
    EvalConfig,
    LoggerConfig,
    MakeDatasetConfig,
    PreparedConfig,
    QConfig,
    RatioConfig,
    WBRMConfig,
    env_config,
    prepare_config,
    register_configs,
    resolve_defaults,
    validate_config,
)
from torchrl_wbrm.training.checkpoint import get_rng_state, set_rng_state, set_seed
from torchrl_wbrm.training.rundir import default_run_dir
from torchrl_wbrm.training.trainer import WBRMTrainer

__all__ = [
    "EvalConfig",
    "LoggerConfig",
    "MakeDatasetConfig",
    "PreparedConfig",
    "QConfig",
    "RatioConfig",
    "WBRMConfig",
    "WBRMTrainer",
    "default_run_dir",
    "env_config",
    "prepare_config",
    "get_rng_state",
    "register_configs",
    "set_rng_state",
    "set_seed",
    "resolve_defaults",
    "validate_config",
]
