"""MountainCarContinuous-v0 (the paper's Section 5.2), torch-native and batched.

A copy of gymnasium's ``Continuous_MountainCarEnv`` under ``TimeLimit(999)`` (what
``gymnasium.make("MountainCarContinuous-v0")`` builds), stepping any number of cars at once. Per step, for the
action ``a`` (shape ``[1]``)::

    force    = clamp(a, -1, 1)
    v'       = clamp(v + 0.0015 force - 0.0025 cos(3 x), -0.07, 0.07)
    x'       = clamp(x + v', -1.2, 0.6)
    v'       = 0                 if x' == -1.2 and v' < 0    (the car stops at the left wall)
    terminated = x' >= 0.45 and v' >= 0
    r        = 100 terminated - 0.1 a^2                    (the *unclipped* action, as gym)

``x_0 ~ U(-0.6, -0.4)``, ``v_0 = 0``; an episode is truncated after 999 steps (gym's ``TimeLimit``), and an
episode that reaches the goal on its 999th step is both terminated and truncated, as in gym.

Precision: gym keeps its state in a float32 array; this env computes each step in float64 from the float32 state
and stores the float32 result (``terminated`` is read on the stored state). One step from the same state agrees with
gym's to float32 rounding (about 1e-7). Gym under NumPy 2 does part of its arithmetic in float32 (NEP 50
promotion), so the two round differently and long open-loop trajectories drift apart slowly: about 1e-6 after
300 steps, 4e-6 after 500 and up to 3e-5 after 999 (largest over 200 random-action episodes).
``tests/test_mountain_car_env.py`` checks both against gym.
"""
from __future__ import annotations

from typing import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Composite, Unbounded

from torchrl_wbrm.envs._batched import BatchedEpisodicEnv, is_int

__all__ = ["MountainCarContinuousEnv"]


class MountainCarContinuousEnv(BatchedEpisodicEnv):
    """Batched, torch-native ``MountainCarContinuous-v0`` (gymnasium's dynamics, reward and 999-step limit).

    Keyword Args:
        batch_size (int or sequence of int): number of independent cars stepped together. Defaults to ``()``.
        device: torch device. Defaults to CPU.
        seed (int, optional): seed of the environment's own generator (the initial positions); ``None`` seeds it
            with 0 (as :class:`~torchrl_wbrm.envs.LQREnv`). ``set_seed`` re-seeds it.
        max_episode_steps (int): steps before truncation. Defaults to 999 (gym's ``TimeLimit``).

    Keys: ``"observation"`` (``[position, velocity]``, float32, within gym's bounds), ``"action"`` (1, bounded
    to ``[-1, 1]``; larger actions are clamped by the dynamics but charged in full by the reward, as in gym),
    ``("next", "reward")`` (1), ``"done"``/``"terminated"``/``"truncated"`` (1).

    The car's state is the observation in the input tensordict (as torchrl's ``PendulumEnv``; write another
    ``"observation"`` to start from any state); the step counter of each car lives in the env, so truncation
    works with partial resets (``"_reset"``) and partial steps (``"_step"``: cars not stepped keep their state,
    their step count and their done flags, with reward 0).

    Examples:
        >>> from torchrl.envs.utils import check_env_specs
        >>> env = MountainCarContinuousEnv(batch_size=[100], seed=0)
        >>> check_env_specs(env)
        >>> rollout = env.rollout(1000, break_when_any_done=False, break_when_all_done=True)  # random actions
        >>> rollout.shape
        torch.Size([100, 999])
        >>> bool(rollout[:, -1]["next", "done"].all())
        True
    """

    MIN_ACTION = -1.0
    MAX_ACTION = 1.0
    MIN_POSITION = -1.2
    MAX_POSITION = 0.6
    MAX_SPEED = 0.07
    GOAL_POSITION = 0.45
    GOAL_VELOCITY = 0.0
    POWER = 0.0015
    GRAVITY = 0.0025  # the hill term: v' = v + POWER force - GRAVITY cos(3 x)
    GOAL_REWARD = 100.0
    ACTION_COST = 0.1
    RESET_LOW = -0.6
    RESET_HIGH = -0.4
    MAX_EPISODE_STEPS = 999

    def __init__(
        self,
        *,
        batch_size: int | Sequence[int] = (),
        device: torch.device | str | None = None,
        seed: int | None = None,
        max_episode_steps: int = MAX_EPISODE_STEPS,
    ):
        if not is_int(max_episode_steps) or max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be a positive integer, got {max_episode_steps!r}.")
        super().__init__(batch_size=batch_size, device=device, seed=seed)
        self.max_episode_steps = int(max_episode_steps)
        self._make_specs()
        self.register_buffer(
            "_goal",
            torch.tensor([self.GOAL_POSITION, self.GOAL_VELOCITY], dtype=torch.float32, device=self.device),
            persistent=False,
        )

    # ------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        bs = self.batch_size
        low = torch.tensor([self.MIN_POSITION, -self.MAX_SPEED], dtype=torch.float32, device=self.device)
        high = torch.tensor([self.MAX_POSITION, self.MAX_SPEED], dtype=torch.float32, device=self.device)
        self.observation_spec = Composite(
            observation=Bounded(
                low=low.expand(*bs, 2),
                high=high.expand(*bs, 2),
                shape=(*bs, 2),
                dtype=torch.float32,
                device=self.device,
            ),
            shape=bs,
        )
        self.action_spec = Bounded(
            low=self.MIN_ACTION, high=self.MAX_ACTION, shape=(*bs, 1), dtype=torch.float32, device=self.device
        )
        self.reward_spec = Unbounded(shape=(*bs, 1), dtype=torch.float32, device=self.device)
        self._make_done_spec()

    # ------------------------------------------------------------------ reset and step
    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        bs = self.batch_size
        u = torch.rand(*bs, 1, generator=self.rng, dtype=torch.float64, device=self.device)
        position = self.RESET_LOW + (self.RESET_HIGH - self.RESET_LOW) * u
        obs = torch.cat([position, torch.zeros_like(position)], -1).to(torch.float32)
        return self._start_episodes(tensordict, obs)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get("observation")
        action = tensordict.get("action").to(torch.float64)
        state = obs.to(torch.float64)
        position, velocity = state[..., 0:1], state[..., 1:2]
        force = action.clamp(self.MIN_ACTION, self.MAX_ACTION)
        velocity = (velocity + force * self.POWER - self.GRAVITY * torch.cos(3 * position)).clamp_(
            -self.MAX_SPEED, self.MAX_SPEED
        )
        position = (position + velocity).clamp_(self.MIN_POSITION, self.MAX_POSITION)
        # at the left wall the car stops: a negative velocity becomes 0
        velocity = torch.where(position == self.MIN_POSITION, velocity.clamp(min=0.0), velocity)
        next_obs = torch.cat([position, velocity], -1).to(torch.float32)  # gym stores its state in float32
        # on the stored state, so that an observation at the goal is a terminal one
        terminated = (next_obs >= self._goal).all(-1, keepdim=True)
        reward = (self.GOAL_REWARD * terminated - self.ACTION_COST * action.square()).to(torch.float32)
        step_mask = self._mask(tensordict, "_step")
        if step_mask is None:
            self._step_count.add_(1)
            truncated = self._step_count >= self.max_episode_steps
        else:  # partial step: the cars not stepped keep their state, step count and flags, with reward 0
            false = torch.zeros_like(terminated)
            next_obs = torch.where(step_mask, next_obs, obs)
            reward = torch.where(step_mask, reward, torch.zeros_like(reward))
            terminated = torch.where(step_mask, terminated, tensordict.get("terminated", false))
            self._step_count.add_(step_mask.to(self._step_count.dtype))
            truncated = torch.where(
                step_mask, self._step_count >= self.max_episode_steps, tensordict.get("truncated", false)
            )
        return TensorDict(
            {
                "observation": next_obs,
                "reward": reward,
                "done": terminated | truncated,
                "terminated": terminated,
                "truncated": truncated,
            },
            batch_size=self.batch_size,
            device=self.device,
        )
