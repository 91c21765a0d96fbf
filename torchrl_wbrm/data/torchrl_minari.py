"""A local Minari dataset as a torchrl replay buffer, in the layout of torchrl's ``MinariExperienceReplay``.

torchrl 0.14.1's own reader, ``torchrl.data.datasets.MinariExperienceReplay(dataset_id, batch_size,
download=False, load_from_local_minari=True)``, reads every observation, action and reward of a Minari 0.5.4 dataset
as 0 (``tests/test_torchrl_minari.py`` records it, and says so the day it reads the values). :func:`minari_replay_buffer`
reads the same dataset with ``minari`` itself (``MinariDataset.iterate_episodes``) and returns a
:class:`~torchrl.data.TensorDictReplayBuffer` with ``MinariExperienceReplay``'s keys, shapes and dtypes:

- ``"observation"`` and ``("next", "observation")``: the episode's observations without its last and first row,
  in the dataset's dtype (a ``Dict`` observation space gives a nested TensorDict, as torchrl's);
- ``"action"``: as stored (a ``Discrete`` action is an integer index of shape ``[N]``, a ``Box`` action ``[N, *shape]``);
- ``("next", "reward")``: ``[N, 1]`` in the dataset's dtype; ``("next", "terminated" | "truncated" | "done")``:
  ``[N, 1]`` bool, ``done = terminated | truncated``;
- ``"episode"``: the Minari episode id of each step, ``[N]`` int64.

Episodes are read in the order of their ids, steps in order; the ``infos`` are not read. The buffer's writer is
torchrl's ``ImmutableDatasetWriter``, as ``MinariExperienceReplay``'s. For this project's own layout (float32, one-hot
``Discrete`` actions, checked values) use :func:`~torchrl_wbrm.data.minari_data.read_minari_transitions`.
"""
from __future__ import annotations

import os

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.data import TensorDictReplayBuffer
from torchrl.data.replay_buffers import ImmutableDatasetWriter, Sampler, TensorStorage

from torchrl_wbrm.keys import EPISODE
from torchrl_wbrm.data.minari_data import resolve_minari_dataset

__all__ = ["minari_replay_buffer", "read_minari_as_torchrl"]


def _as_tensor(value):
    """A Minari array (or a dict of them, for a ``Dict`` space) as a tensor (or a dict of tensors), dtype kept."""
    if isinstance(value, dict):
        return {key: _as_tensor(item) for key, item in value.items()}
    return torch.as_tensor(np.asarray(value))


def _rows(value, start: int, stop: int | None):
    if isinstance(value, dict):
        return {key: _rows(item, start, stop) for key, item in value.items()}
    return value[start:stop]


def read_minari_as_torchrl(dataset_id: str, *, data_path: str | os.PathLike | None = None) -> TensorDict:
    """Every step of the local Minari dataset ``dataset_id`` (an id under ``data_path`` / ``MINARI_DATASETS_PATH``,
    or a dataset folder) as one TensorDict ``[N]`` in ``MinariExperienceReplay``'s layout (see the module's
    docstring). Never downloads; a missing dataset is a ``FileNotFoundError`` naming it and the folder searched, an
    episode whose observations are not one more than its steps a ``ValueError`` naming the episode."""
    from minari.dataset.minari_dataset import MinariDataset

    dataset = MinariDataset(str(resolve_minari_dataset(dataset_id, data_path)))
    parts = []
    for episode in sorted(dataset.iterate_episodes(), key=lambda e: int(e.id)):
        steps = len(episode.rewards)
        if steps == 0:
            continue
        observations = _as_tensor(episode.observations)
        first = next(iter(observations.values())) if isinstance(observations, dict) else observations
        if first.shape[0] != steps + 1:
            raise ValueError(f"Minari dataset {dataset_id!r}: episode {episode.id} has {first.shape[0]} observations "
                             f"for {steps} steps (expected {steps + 1}).")
        terminated = torch.as_tensor(np.asarray(episode.terminations, dtype=bool)).reshape(steps, 1)
        truncated = torch.as_tensor(np.asarray(episode.truncations, dtype=bool)).reshape(steps, 1)
        parts.append(TensorDict({
            "observation": _rows(observations, 0, -1),
            "action": _as_tensor(episode.actions),
            EPISODE: torch.full((steps,), int(episode.id), dtype=torch.int64),
            "next": {
                "observation": _rows(observations, 1, None),
                "reward": _as_tensor(episode.rewards).reshape(steps, 1),
                "terminated": terminated,
                "truncated": truncated,
                "done": terminated | truncated,
            },
        }, batch_size=[steps]))
    if not parts:
        raise ValueError(f"Minari dataset {dataset_id!r} holds no steps ({dataset.total_episodes} episodes).")
    return torch.cat(parts, 0)


def minari_replay_buffer(
    dataset_id: str,
    batch_size: int,
    *,
    data_path: str | os.PathLike | None = None,
    sampler: Sampler | None = None,
    transform=None,
) -> TensorDictReplayBuffer:
    """The local Minari dataset ``dataset_id`` as a torchrl :class:`~torchrl.data.TensorDictReplayBuffer` with
    ``MinariExperienceReplay``'s keys and layout (:func:`read_minari_as_torchrl`), over a ``TensorStorage`` of the
    steps, with an ``ImmutableDatasetWriter``; ``batch_size``, ``sampler`` and ``transform`` as for any replay
    buffer.

    Examples:
        >>> import tempfile
        >>> from torchrl_wbrm.data.minari_examples import collect_gym_episodes
        >>> from torchrl_wbrm.data import write_minari_dataset
        >>> folder = tempfile.mkdtemp()
        >>> episodes = collect_gym_episodes("CartPole-v1", lambda obs, rng: int(rng.integers(0, 2)), 2, seed=0)
        >>> _ = write_minari_dataset("doc/cartpole-v0", episodes, data_path=folder, env="CartPole-v1")
        >>> rb = minari_replay_buffer("doc/cartpole-v0", 8, data_path=folder)
        >>> batch = rb.sample()
        >>> batch["action"].shape, batch["next", "reward"].shape, batch["next", "done"].dtype
        (torch.Size([8]), torch.Size([8, 1]), torch.bool)
    """
    data = read_minari_as_torchrl(dataset_id, data_path=data_path)
    return TensorDictReplayBuffer(storage=TensorStorage(data), writer=ImmutableDatasetWriter(), sampler=sampler,
                                  batch_size=batch_size, transform=transform)
