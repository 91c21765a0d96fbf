"""Offline datasets for MountainCarContinuous-v0, in the paper's shape (Section 5.2).

Expert: the noisy heuristic (:func:`~torchrl_wbrm.policies.make_mountain_car_expert`, tau = 0.1), 20K
transitions -> ``S^e``. Behaviour: whole episodes of uniform random actions plus whole expert episodes, about
100K transitions, split by episode into ``D`` and ``S^b``.

Collection runs on the torch-native, batched env (:class:`~torchrl_wbrm.envs.MountainCarContinuousEnv`, a copy of
gym's), ``parallel_envs`` cars at a time.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from torchrl_wbrm.keys import EPISODE
from torchrl_wbrm.data.datasets import OfflineDatasets, collect_transitions, episode_returns
from torchrl_wbrm.policies import make_mountain_car_env, make_mountain_car_expert, make_mountain_car_random_policy

__all__ = ["MountainCarDataConfig", "make_mountain_car_datasets"]


@dataclass
class MountainCarDataConfig:
    """Sizes of a MountainCar offline dataset (paper: 20K expert, about 100K behaviour transitions).

    Attributes:
        expert_transitions: expert transitions for ``S^e``.
        behaviour_transitions: behaviour transitions in all (``D`` and ``S^b``).
        random_fraction: share of the behaviour transitions from random-action episodes (the rest are expert
            episodes with the behaviour's own seed).
        ratio_fraction: fraction of the behaviour episodes that go to ``S^b``.
        expert_tau: the expert's noise mix.
        expert_power: the expert's push strength.
        parallel_envs: cars stepped at once while collecting. A collector over ``N`` cars and ``F`` frames runs
            each car ``F / N`` steps, and the episode each car is in when the collection stops is cut (it stays in
            the data; :func:`~torchrl_wbrm.data.episode_returns` skips it). So ``N`` must stay small enough that
            episodes are mostly whole: each collection uses ``min(parallel_envs, max(1, F // 1000))`` cars, at
            least one full-length (999-step) episode's worth of steps per car; the defaults give 10 cars with
            5000 (behaviour) and 2000 (expert) steps each.
    """

    expert_transitions: int = 20_000
    behaviour_transitions: int = 100_000
    random_fraction: float = 0.5
    ratio_fraction: float = 0.2
    expert_tau: float = 0.1
    expert_power: float = 1.0
    parallel_envs: int = 10


def make_mountain_car_datasets(
    data: MountainCarDataConfig | None = None, *, seed: int = 0, storage: str = "lazy", scratch_dir=None
) -> OfflineDatasets:
    """Collect the behaviour (random then expert episodes) and expert sets, and split the behaviour by episode.

    Episode ids are unique over the whole behaviour set (the expert part's are shifted past the random part's), so
    the split into ``D`` and ``S^b`` keeps episodes whole. Metadata records the mean undiscounted returns of the
    complete episodes.
    """
    data = MountainCarDataConfig() if data is None else data
    if not 0.0 <= data.random_fraction <= 1.0:
        raise ValueError(f"random_fraction must lie in [0, 1], got {data.random_fraction}.")
    if isinstance(data.parallel_envs, bool) or int(data.parallel_envs) != data.parallel_envs or data.parallel_envs < 1:
        raise ValueError(f"parallel_envs must be a positive integer, got {data.parallel_envs!r}.")

    def collect(policy_for, frames: int, part_seed: int, episode_offset: int = 0):
        n_envs = min(int(data.parallel_envs), max(1, frames // 1000))
        env = make_mountain_car_env(seed=part_seed, batch_size=[n_envs])
        out = collect_transitions(env, policy_for(env), frames, seed=part_seed, episode_offset=episode_offset)
        env.close()
        return out

    def expert_policy(env):
        return make_mountain_car_expert(power=data.expert_power, tau=data.expert_tau)

    def random_policy(env):
        return make_mountain_car_random_policy(env.action_spec)

    n_random = int(round(data.random_fraction * data.behaviour_transitions))
    n_expert_b = data.behaviour_transitions - n_random
    parts = []
    if n_random > 0:
        parts.append(collect(random_policy, n_random, seed))
    if n_expert_b > 0:
        offset = 0 if not parts else int(parts[-1][EPISODE].max()) + 1
        parts.append(collect(expert_policy, n_expert_b, seed + 1, episode_offset=offset))
    behaviour = torch.cat(parts, 0)
    expert = collect(expert_policy, data.expert_transitions, seed + 2)
    metadata = {
        "env": "mountain_car",
        "data_config": vars(data),
        "seed": seed,
        "behaviour_mean_return": episode_returns(behaviour).mean().item(),
        "expert_mean_return": episode_returns(expert).mean().item(),
    }
    return OfflineDatasets.from_behaviour_and_expert(
        behaviour,
        expert.select("observation", "action", EPISODE),
        ratio_fraction=data.ratio_fraction,
        generator=torch.Generator().manual_seed(seed + 3),
        metadata=metadata,
        storage=storage,
        scratch_dir=scratch_dir,
    )
