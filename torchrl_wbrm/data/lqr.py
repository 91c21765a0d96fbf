"""Offline datasets for the LQR system: behaviour and expert episodes collected on the batched env."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

import torch

from torchrl_wbrm.keys import EPISODE
from torchrl_wbrm.data.datasets import OfflineDatasets, collect_transitions, episode_returns
from torchrl_wbrm.envs import LQRConfig, LQREnv, make_lqr_env
from torchrl_wbrm.policies import make_lqr_behaviour, make_lqr_expert

__all__ = ["LQRDataConfig", "behaviour_system", "make_lqr_datasets"]


@dataclass
class LQRDataConfig:
    """Sizes and policies of an LQR offline dataset.

    Attributes:
        behaviour_episodes: episodes of the behaviour policy (each ``horizon`` transitions); split by episode
            into ``D`` and ``S^b``.
        expert_episodes: episodes of the expert (all go to ``S^e``).
        ratio_fraction: fraction of the behaviour episodes that go to ``S^b``.
        expert_tau: the paper's ``tau``: expert ``a = (1 - tau)(-Kx) + tau N(0, I)`` (paper: 0.05).
        behaviour_gain_scale: behaviour ``a = -scale K x + N(0, noise^2 I)``.
        behaviour_noise_std: see above.
        behaviour_initial_std: the behaviour episodes start from ``x_0 ~ N(0, behaviour_initial_std^2 I)``
            (``None``: the system's ``env.lqr.initial_std``, as the expert's and the evaluation's do). Another value
            shifts the behaviour data's start distribution away from the one the policy is scored on; the exact
            ratio and the behaviour samples Q̂ is scored on follow it.
        parallel_envs: systems stepped at once while collecting.
        storage: ``"lazy"`` (the sets' replay buffers in RAM) or ``"memmap"`` (``LazyMemmapStorage``, on disk).
        dataset_dir: a dataset saved by :meth:`OfflineDatasets.save` (``recipes/make_dataset.py``) to train on instead
            of collecting one; it is loaded (and verified) into ``storage``. The sizes and policies above are then
            not used.
    """

    behaviour_episodes: int = 2000
    expert_episodes: int = 1000
    ratio_fraction: float = 0.5
    expert_tau: float = 0.05
    behaviour_gain_scale: float = 0.5
    behaviour_noise_std: float = 0.5
    behaviour_initial_std: Optional[float] = None
    parallel_envs: int = 1000
    storage: str = "lazy"
    dataset_dir: Optional[str] = None


def behaviour_system(system: LQRConfig, data: LQRDataConfig) -> LQRConfig:
    """The system the behaviour episodes run on: ``system`` itself, or with the start law
    ``N(0, data.behaviour_initial_std^2 I)`` when that is set (a shifted start distribution; same dynamics)."""
    return system if data.behaviour_initial_std is None else replace(system, initial_std=data.behaviour_initial_std)


def make_lqr_datasets(
    experiment: str | LQRConfig = "exp1",
    data: LQRDataConfig | None = None,
    *,
    seed: int = 0,
    storage: str = "lazy",
    scratch_dir=None,
) -> OfflineDatasets:
    """Collect behaviour and expert episodes with torchrl's ``Collector`` and split them as the paper requires.

    The behaviour episodes are split by episode into ``D`` (transitions) and ``S^b``; expert episodes give
    ``S^e``. Metadata records the policies and the measured mean discounted returns.

    Examples:
        >>> ds = make_lqr_datasets("exp1", LQRDataConfig(behaviour_episodes=100, expert_episodes=50), seed=0)
        >>> ds.sizes()
        {'transitions': 1000, 'behaviour_samples': 1000, 'expert_samples': 1000}
    """
    data = LQRDataConfig() if data is None else data
    if data.behaviour_episodes < 2 or data.expert_episodes < 1:
        raise ValueError(
            f"Need behaviour_episodes >= 2 and expert_episodes >= 1, got {data.behaviour_episodes} and "
            f"{data.expert_episodes}."
        )
    system = LQREnv(experiment).config  # a paper experiment's name or an LQRConfig, resolved as the env does

    def env_for(episodes: int, env_seed: int, config: LQRConfig):
        return make_lqr_env(config, batch_size=[min(data.parallel_envs, episodes)], seed=env_seed)

    env_b = env_for(data.behaviour_episodes, seed, behaviour_system(system, data))
    horizon = env_b.base_env.config.horizon
    gamma = env_b.base_env.config.gamma
    behaviour_policy = make_lqr_behaviour(
        env_b, gain_scale=data.behaviour_gain_scale, noise_std=data.behaviour_noise_std
    )
    behaviour = collect_transitions(env_b, behaviour_policy, data.behaviour_episodes * horizon, seed=seed)
    env_e = env_for(data.expert_episodes, seed + 1, system)
    expert_policy = make_lqr_expert(env_e, tau=data.expert_tau)
    expert = collect_transitions(env_e, expert_policy, data.expert_episodes * horizon, seed=seed + 1)
    config = env_e.base_env.config  # the system's own (its start law is the expert's and the evaluation's)
    metadata = {
        "env": "lqr",
        "lqr_config": config.to_dict(),
        "data_config": vars(data),
        "seed": seed,
        "behaviour_policy": repr(behaviour_policy.module),
        "expert_policy": repr(expert_policy.module),
        "behaviour_mean_return": episode_returns(behaviour, gamma=gamma).mean().item(),
        "expert_mean_return": episode_returns(expert, gamma=gamma).mean().item(),
        "optimal_return": env_e.base_env.optimal_return(),
    }
    generator = torch.Generator().manual_seed(seed + 2)
    return OfflineDatasets.from_behaviour_and_expert(
        behaviour,
        expert.select("observation", "action", EPISODE, "step_count", strict=False),
        ratio_fraction=data.ratio_fraction,
        generator=generator,
        metadata=metadata,
        storage=storage,
        scratch_dir=scratch_dir,
    )
