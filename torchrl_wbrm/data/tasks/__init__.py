"""One task object per environment kind: everything env-specific the trainer, the algos and the recipes need (the
data, the action box, γ, the evaluator, the ground truth, the config checks), so none of them branches on the env.

``get_task(env_config)`` is the one place that maps ``env.kind`` to its task. A new env kind is a :class:`Task`
subclass registered with :func:`register_task`.
"""
from __future__ import annotations

from torchrl_wbrm.data.tasks.base import Evaluator, Task, to_dataclass
from torchrl_wbrm.data.tasks.lqr import LQREvaluator, LQRTask
from torchrl_wbrm.data.tasks.minari import MinariEvaluator, MinariTask
from torchrl_wbrm.data.tasks.mountain_car import MountainCarEvaluator, MountainCarTask

__all__ = [
    "TASKS",
    "Evaluator",
    "LQREvaluator",
    "LQRTask",
    "MinariEvaluator",
    "MinariTask",
    "MountainCarEvaluator",
    "MountainCarTask",
    "Task",
    "get_task",
    "register_task",
    "to_dataclass",
]

#: env.kind -> its :class:`Task` class
TASKS: dict[str, type[Task]] = {}


def register_task(cls: type[Task]) -> type[Task]:
    """Class decorator: register a :class:`Task` subclass under its ``kind``."""
    if not cls.kind or cls.kind in TASKS:
        raise ValueError(f"register_task: {cls.__name__}.kind must be a new, non-empty name, got {cls.kind!r}.")
    TASKS[cls.kind] = cls
    return cls


for _task in (LQRTask, MountainCarTask, MinariTask):
    register_task(_task)


def get_task(env) -> Task:
    """The task of ``env`` (an :class:`~torchrl_wbrm.data.EnvConfig`, or an OmegaConf/dict node of one)."""
    if isinstance(env, dict):
        from omegaconf import OmegaConf

        env = OmegaConf.create(env)
    kind = env.kind
    if kind not in TASKS:
        raise ValueError(f"env.kind={kind!r} is not known: choose one of {list(TASKS)}.")
    return TASKS[kind](env)
