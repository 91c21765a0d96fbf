"""Offline datasets for MountainCarContinuous-v0, in the paper's shape (Section 5.2).

Expert: the noisy heuristic (:func:`~torchrl_wbrm.policies.make_mountain_car_expert`, tau = 0.1), 20K
transitions -> ``S^e``. Behaviour: whole episodes of uniform random actions plus whole expert episodes, about
100K transitions, split by episode into ``D`` and ``S^b``.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

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
    """

    expert_transitions: int = 20_000
    behaviour_transitions: int = 100_000
    random_fraction: float = 0.5
    ratio_fraction: float = 0.2
    expert_tau: float = 0.1
    expert_power: float = 1.0


def make_mountain_car_datasets(
    data: MountainCarDataConfig | None = None, *, seed: int = 0, storage: str = "lazy", scratch_dir=None
) -> OfflineDatasets:
    data = MountainCarDataConfig() if data is None else data
    if not 0.0 <= data.random_fraction <= 1.0:
        raise ValueError(f"random_fraction must lie in [0, 1], got {data.random_fraction}.")
    env = make_mountain_car_env(seed=seed)
    expert_policy = make_mountain_car_expert(power=data.expert_power, tau=data.expert_tau)
    n_random = int(round(data.random_fraction * data.behaviour_transitions))
    n_expert_b = data.behaviour_transitions - n_random
    parts = []
    if n_random > 0:
        random_policy = make_mountain_car_random_policy(env.action_spec)
        parts.append(collect_transitions(env, random_policy, n_random, seed=seed))
    if n_expert_b > 0:
        offset = 0 if not parts else int(parts[-1]["episode"].max()) + 1
        parts.append(collect_transitions(env, expert_policy, n_expert_b, seed=seed + 1, episode_offset=offset))
    behaviour = torch.cat(parts, 0)
    expert = collect_transitions(env, expert_policy, data.expert_transitions, seed=seed + 2)
    env.close()
    metadata = {
        "env": "mountain_car",
        "data_config": vars(data),
        "seed": seed,
        "behaviour_mean_return": episode_returns(behaviour).mean().item(),
        "expert_mean_return": episode_returns(expert).mean().item(),
    }
    return OfflineDatasets.from_behaviour_and_expert(
        behaviour,
        expert.select("observation", "action", "episode"),
        ratio_fraction=data.ratio_fraction,
        generator=torch.Generator().manual_seed(seed + 3),
        metadata=metadata,
        storage=storage,
        scratch_dir=scratch_dir,
    )
