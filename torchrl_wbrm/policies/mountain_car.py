"""Expert and behaviour policies for MountainCarContinuous-v0 (Section 5.2 of the paper).

Expert: a closed-form heuristic from the gym leaderboard family, "push along the velocity": full power in the
direction the car moves (at rest, push left, which starts the swing from the valley), mixed with noise as in the
paper's Eq. "pi^e = (1 - tau) pi* + tau eps" read as a convex combination of actions:
``a = (1 - tau) * power * direction + tau * U(-1, 1)`` with ``tau = 0.1``. ``power < 1`` spends less on the
-0.1 a^2 action cost. ``python recipes/policy_returns.py`` measures each policy's return.

Behaviour: "random actions plus expert episodes". :func:`make_mountain_car_random_policy` draws uniform actions
in the action spec; the data layer mixes whole episodes of it with expert episodes.

Env: :func:`make_mountain_car_env` builds the torch-native, batched copy of gym's env
(:class:`~torchrl_wbrm.envs.MountainCarContinuousEnv`); :func:`make_mountain_car_gym_env` builds gym's own, through
torchrl's ``GymEnv`` (one car at a time, far slower).
"""
from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType, exploration_type

from torchrl_wbrm.envs.mountain_car import MountainCarContinuousEnv

__all__ = [
    "MountainCarHeuristic",
    "make_mountain_car_expert",
    "make_mountain_car_random_policy",
    "make_mountain_car_env",
    "make_mountain_car_gym_env",
]

ENV_NAME = "MountainCarContinuous-v0"


def make_mountain_car_env(*, seed: int | None = None, device=None, batch_size=None):
    """The torch-native, batched ``MountainCarContinuous-v0``
    (:class:`~torchrl_wbrm.envs.MountainCarContinuousEnv`: gym's dynamics, 999-step episodes, +100 at the goal,
    -0.1 a^2 per step).

    Args:
        seed: seed of the env's generator (initial positions); ``None``: 0.
        device: torch device.
        batch_size: cars stepped together (``[N]`` runs ``N`` episodes at once); ``None``: ``[]``, one car, as gym.
    """
    return MountainCarContinuousEnv(batch_size=() if batch_size is None else batch_size, device=device, seed=seed)


def make_mountain_car_gym_env(*, seed: int | None = None, device=None):
    """``GymEnv("MountainCarContinuous-v0")``: gymnasium itself (one car; the reference the torch env reproduces)."""
    from torchrl.envs import GymEnv

    env = GymEnv(ENV_NAME, device=device)
    if seed is not None:
        env.set_seed(seed)
    return env


class MountainCarHeuristic(nn.Module):
    """``a = (1 - tau) * power * direction(v) + tau * U(-1, 1)``, ``direction = sign(v)`` (``-1`` at rest).

    Under ``DETERMINISTIC`` exploration the noise is dropped.
    """

    def __init__(self, *, power: float = 1.0, tau: float = 0.1, generator: torch.Generator | None = None):
        super().__init__()
        if not 0.0 < power <= 1.0:
            raise ValueError(f"power must lie in (0, 1] (the action bound), got {power}.")
        if not 0.0 <= tau <= 1.0:
            raise ValueError(f"tau must lie in [0, 1], got {tau}.")
        self.power, self.tau, self.generator = float(power), float(tau), generator

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        velocity = observation[..., 1:2]
        direction = torch.where(velocity > 0, 1.0, -1.0).to(observation.dtype)
        push = self.power * direction
        if self.tau == 0 or exploration_type() in (ExplorationType.DETERMINISTIC, ExplorationType.MODE):
            return push
        noise = 2 * torch.rand(push.shape, generator=self.generator, dtype=push.dtype, device=push.device) - 1
        return (1 - self.tau) * push + self.tau * noise

    def extra_repr(self) -> str:
        return f"power={self.power}, tau={self.tau}"


def make_mountain_car_expert(*, power: float = 1.0, tau: float = 0.1, generator=None) -> TensorDictModule:
    return TensorDictModule(
        MountainCarHeuristic(power=power, tau=tau, generator=generator), in_keys=["observation"], out_keys=["action"]
    )


def make_mountain_car_random_policy(action_spec):
    """Uniform actions in the action spec (torchrl's ``RandomPolicy``)."""
    from torchrl.envs.utils import RandomPolicy

    return RandomPolicy(action_spec)
