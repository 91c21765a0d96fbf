"""One task object per environment kind, a floor above the data readers (``torchrl_wbrm.data``): everything
env-specific the trainer, the algos and the recipes need (the data, the action box, γ, the evaluator, the ground
truth, the config checks, the training defaults), so none of them branches on the env.

``get_task(env_config)`` is the one place that maps ``env.kind`` to its task. A new env kind is a :class:`Task`
subclass registered with :func:`register_task`; :func:`make_offline_datasets` goes from an env config to its data.
"""
from __future__ import annotations

from torchrl_wbrm.tasks.base import EvalDefaults, Evaluator, QDefaults, Task, TrainingDefaults, to_dataclass
from torchrl_wbrm.tasks.factory import ENV_KINDS, EnvConfig, cached_offline_datasets, make_offline_datasets
from torchrl_wbrm.tasks.lqr import LQREvaluator, LQRTask
from torchrl_wbrm.tasks.minari import MinariEvaluator, MinariTask
from torchrl_wbrm.tasks.mountain_car import MountainCarEvaluator, MountainCarTask
from torchrl_wbrm.tasks.registry import TASKS, get_task, register_task

__all__ = [
    "ENV_KINDS",
    "TASKS",
    "EnvConfig",
    "EvalDefaults",
    "Evaluator",
    "LQREvaluator",
    "LQRTask",
    "MinariEvaluator",
    "MinariTask",
    "MountainCarEvaluator",
    "MountainCarTask",
    "QDefaults",
    "Task",
    "TrainingDefaults",
    "cached_offline_datasets",
    "get_task",
    "make_offline_datasets",
    "register_task",
    "to_dataclass",
]
