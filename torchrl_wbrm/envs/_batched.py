"""What the project's torch-native envs share: batch and seed checks, an own generator, the per-env step counter,
the ``done``/``terminated``/``truncated`` spec and (partial) resets."""
from __future__ import annotations

import numbers
from typing import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Composite
from torchrl.envs import EnvBase

__all__ = ["BatchedEpisodicEnv", "is_int"]


def is_int(value) -> bool:
    """An integer that is not a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


class BatchedEpisodicEnv(EnvBase):
    """A batched ``EnvBase`` with its own ``torch.Generator`` (``self.rng``; seed ``None`` means 0) and a per-env
    step counter (``self._step_count``, shape ``[*batch, 1]``).

    Subclasses build their specs (calling :meth:`_make_done_spec` for the flags), draw a fresh observation for every
    env in ``_reset`` and return :meth:`_start_episodes` of it; ``_step`` advances ``self._step_count``.
    """

    batch_locked = True

    def __init__(
        self, *, batch_size: int | Sequence[int] = (), device: torch.device | str | None = None, seed: int | None = None
    ):
        if is_int(batch_size):
            batch_size = (batch_size,)
        if not isinstance(batch_size, Sequence) or not all(is_int(n) for n in batch_size):
            raise TypeError(f"batch_size must be an int or a sequence of ints, got {batch_size!r}.")
        if any(n < 1 for n in batch_size):
            raise ValueError(f"batch_size must hold positive sizes, got {tuple(batch_size)}.")
        if seed is not None and not is_int(seed):
            raise TypeError(f"seed must be an int or None, got {seed!r}.")
        super().__init__(device=device, batch_size=torch.Size([int(n) for n in batch_size]))
        self.rng = torch.Generator(device=self.device)
        self.register_buffer(
            "_step_count", torch.zeros(*self.batch_size, 1, dtype=torch.int64, device=self.device), persistent=False
        )
        self._set_seed(0 if seed is None else seed)

    def _make_done_spec(self) -> None:
        bs = self.batch_size
        flag = Categorical(2, shape=(*bs, 1), dtype=torch.bool, device=self.device)
        self.done_spec = Composite(done=flag, terminated=flag.clone(), truncated=flag.clone(), shape=bs)

    def _set_seed(self, seed: int | None) -> None:
        self.rng.manual_seed(int(seed) if seed is not None else torch.seed())

    def _mask(self, tensordict: TensorDictBase | None, key: str) -> torch.Tensor | None:
        """``tensordict[key]`` (``"_reset"`` or ``"_step"``) as a ``[*batch, 1]`` mask, or ``None`` if absent."""
        if tensordict is None:
            return None
        mask = tensordict.get(key, None)
        return None if mask is None else mask.reshape(*self.batch_size, 1)

    def _start_episodes(self, tensordict: TensorDictBase | None, observation: torch.Tensor) -> TensorDictBase:
        """The reset output for a fresh ``observation`` of every env: a masked reset (``"_reset"``) keeps the other
        envs' observation and step count; a full one (or one without the previous state) restarts all."""
        reset_mask = self._mask(tensordict, "_reset")
        previous = None if tensordict is None else tensordict.get("observation", None)
        if reset_mask is not None and previous is not None:
            observation = torch.where(reset_mask, observation, previous)
            self._step_count = torch.where(reset_mask, torch.zeros_like(self._step_count), self._step_count)
        else:
            self._step_count = torch.zeros_like(self._step_count)
        false = torch.zeros(*self.batch_size, 1, dtype=torch.bool, device=self.device)
        return TensorDict(
            {"observation": observation, "done": false, "terminated": false.clone(), "truncated": false.clone()},
            batch_size=self.batch_size,
            device=self.device,
        )
