"""The registered tasks: ``env.kind`` -> its :class:`~torchrl_wbrm.tasks.Task` class, and :func:`get_task`."""
from __future__ import annotations

from torchrl_wbrm.tasks.base import Task
from torchrl_wbrm.tasks.lqr import LQRTask
from torchrl_wbrm.tasks.minari import MinariTask
from torchrl_wbrm.tasks.mountain_car import MountainCarTask

__all__ = ["TASKS", "get_task", "register_task"]

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
    """The task of ``env`` (an :class:`~torchrl_wbrm.tasks.EnvConfig`, or an OmegaConf/dict node of one)."""
    if isinstance(env, dict):
        from omegaconf import OmegaConf

        env = OmegaConf.create(env)
    kind = env.kind
    if kind not in TASKS:
        raise ValueError(f"env.kind={kind!r} is not known: choose one of {list(TASKS)}.")
    return TASKS[kind](env)
