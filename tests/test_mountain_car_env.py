"""MountainCarContinuousEnv: specs, step-by-step equivalence with gymnasium, truncation, resets, seeding, returns."""
from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.envs import GymEnv
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type

from torchrl_wbrm.envs import MountainCarContinuousEnv
from torchrl_wbrm.evaluation import discounted_returns
from torchrl_wbrm.policies import make_mountain_car_env, make_mountain_car_expert
from torchrl_wbrm.policies.mountain_car import ENV_NAME, make_mountain_car_gym_env

E = MountainCarContinuousEnv


@pytest.mark.parametrize("batch_size", [(), (4,), (2, 3)])
def test_check_env_specs(batch_size):
    env = MountainCarContinuousEnv(batch_size=batch_size, seed=0)
    check_env_specs(env)
    obs = env.observation_spec["observation"]
    assert obs.dtype == torch.float32 and obs.shape == (*batch_size, 2)
    torch.testing.assert_close(obs.space.low.reshape(-1, 2)[0], torch.tensor([-1.2, -0.07]))
    torch.testing.assert_close(obs.space.high.reshape(-1, 2)[0], torch.tensor([0.6, 0.07]))
    assert env.action_spec.shape == (*batch_size, 1)
    assert (env.action_spec.space.low == -1).all() and (env.action_spec.space.high == 1).all()
    assert env.reward_spec.shape == (*batch_size, 1)
    assert set(env.done_keys) == {"done", "terminated", "truncated"}
    for key in env.done_keys:
        assert env.full_done_spec[key].dtype == torch.bool and env.full_done_spec[key].shape == (*batch_size, 1)


def test_constants_match_gym():
    g = gym.make(ENV_NAME)
    u = g.unwrapped
    assert (E.MIN_ACTION, E.MAX_ACTION) == (u.min_action, u.max_action)
    assert (E.MIN_POSITION, E.MAX_POSITION, E.MAX_SPEED) == (u.min_position, u.max_position, u.max_speed)
    assert (E.GOAL_POSITION, E.GOAL_VELOCITY, E.POWER) == (u.goal_position, u.goal_velocity, u.power)
    assert E.MAX_EPISODE_STEPS == g.spec.max_episode_steps == 999
    g.close()


# ---------------------------------------------------------------------- equivalence with gymnasium
def _drive_both(x0s, policy, steps: int, *, resync: bool = False, atol: float = 1e-5):
    """Step gym's envs (``gym.make``: TimeLimit(999) included) and one batched env from the same float32 states.

    ``policy(t, obs)`` maps gym's observations ``[B, 2]`` to float32 actions ``[B, 1]``; both envs get the same
    actions. Observations, rewards, ``terminated`` and ``truncated`` must agree at every step of every episode until
    it ends. ``resync=True`` restarts each step of the torch env from gym's state (one-step agreement).
    Returns per-car counters: steps run, terminated, truncated, left-wall hits, final reward.
    """
    x0s = np.asarray(x0s, dtype=np.float32)
    n = len(x0s)
    gyms = [gym.make(ENV_NAME) for _ in range(n)]
    state = np.stack([x0s, np.zeros_like(x0s)], -1)
    for g, s in zip(gyms, state):
        g.reset(seed=0)
        g.unwrapped.state = s.copy()
    env = MountainCarContinuousEnv(batch_size=[n], seed=0)
    td = env.reset()
    td["observation"] = torch.from_numpy(state.copy())
    alive = np.ones(n, dtype=bool)
    stats = {k: np.zeros(n, dtype=np.int64) for k in ("steps", "terminated", "truncated", "wall")}
    stats["reward"] = np.zeros(n)
    obs_g = state.copy()
    for t in range(steps):
        action = np.asarray(policy(t, obs_g), dtype=np.float32).reshape(n, 1)
        if resync:
            td["observation"] = torch.from_numpy(obs_g.copy())
        rew_g, term_g, trunc_g = np.zeros(n), np.zeros(n, bool), np.zeros(n, bool)
        for i in np.flatnonzero(alive):
            obs_g[i], rew_g[i], term_g[i], trunc_g[i], _ = gyms[i].step(action[i])
        td["action"] = torch.from_numpy(action)
        nxt = env.step(td)["next"]
        idx = np.flatnonzero(alive)
        np.testing.assert_allclose(nxt["observation"].numpy()[idx], obs_g[idx], rtol=0, atol=atol, err_msg=f"step {t}")
        np.testing.assert_allclose(nxt["reward"].numpy()[idx, 0], rew_g[idx], rtol=0, atol=atol, err_msg=f"step {t}")
        np.testing.assert_array_equal(nxt["terminated"].numpy()[idx, 0], term_g[idx], err_msg=f"step {t}")
        np.testing.assert_array_equal(nxt["truncated"].numpy()[idx, 0], trunc_g[idx], err_msg=f"step {t}")
        np.testing.assert_array_equal(nxt["done"].numpy()[idx, 0], term_g[idx] | trunc_g[idx])
        stats["steps"][idx] += 1
        stats["wall"][idx] += obs_g[idx, 0] <= E.MIN_POSITION
        stats["terminated"][idx] |= term_g[idx]
        stats["truncated"][idx] |= trunc_g[idx]
        stats["reward"][idx] = rew_g[idx]
        alive &= ~(term_g | trunc_g)
        td = nxt
        if not alive.any():
            break
    for g in gyms:
        g.close()
    return stats


def _random_actions(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    return lambda t, obs: rng.uniform(-1.2, 1.2, size=(n, 1))  # beyond the bounds: the clamp and the full cost


def test_random_actions_match_gym_for_hundreds_of_steps():
    x0s = np.linspace(-0.6, -0.4, 8)
    stats = _drive_both(x0s, _random_actions(8), 500)
    assert (stats["steps"] == 500).all()


def test_random_actions_match_gym_step_by_step_to_truncation():
    """Restarted from gym's state each step, the two agree to float32 rounding over whole 999-step episodes."""
    x0s = np.linspace(-0.6, -0.4, 4)
    stats = _drive_both(x0s, _random_actions(4, seed=1), 1000, resync=True, atol=5e-7)
    assert (stats["steps"] == 999).all() and stats["truncated"].all() and not stats["terminated"].any()


@pytest.mark.parametrize("amplitude", [1.0, 1.2])
def test_bang_bang_reaches_the_goal_like_gym(amplitude):
    x0s = np.array([-0.6, -0.55, -0.5, -0.45, -0.4])
    stats = _drive_both(x0s, lambda t, obs: np.where(obs[:, 1:2] > 0, amplitude, -amplitude), 999)
    assert stats["terminated"].all() and not stats["truncated"].any()
    assert (stats["steps"] < 120).all()
    np.testing.assert_allclose(stats["reward"], 100 - 0.1 * amplitude**2, atol=1e-5)  # +100 and the unclipped cost


def test_left_wall_matches_gym():
    """Swing, but push left past x = -0.3: the car never reaches the goal and hits the left wall again and again."""
    x0s = np.array([-0.6, -0.5, -0.4])
    policy = lambda t, obs: np.where(obs[:, 0:1] > -0.3, -1.0, np.where(obs[:, 1:2] > 0, 1.0, -1.0))  # noqa: E731
    stats = _drive_both(x0s, policy, 400)
    assert (stats["wall"] >= 3).all() and not stats["terminated"].any()


def test_wall_stops_the_car_and_goal_terminates():
    env = MountainCarContinuousEnv(batch_size=[3])
    td = env.reset()
    td["observation"] = torch.tensor([[-1.19, -0.05], [0.44, 0.03], [0.5, -0.01]])
    td["action"] = torch.tensor([[-1.0], [5.0], [0.0]])
    out = env.step(td)["next"]
    assert out["observation"][0].tolist() == [pytest.approx(-1.2), 0.0]
    assert out["terminated"].squeeze(-1).tolist() == [False, True, False]  # past 0.45 moving left: not a goal
    # the action 5 moves the car as 1 but costs 0.1 * 25
    torch.testing.assert_close(out["reward"][1], torch.tensor([100.0 - 2.5]))


# ---------------------------------------------------------------------- episodes, resets, seeding
def test_truncation_at_exactly_999_steps():
    env = make_mountain_car_env(batch_size=[3], seed=0)
    rollout = env.rollout(2000, lambda td: td.set("action", torch.zeros(3, 1)))
    assert rollout.shape == (3, 999)
    truncated, terminated = rollout["next", "truncated"].squeeze(-1), rollout["next", "terminated"].squeeze(-1)
    assert truncated[:, -1].all() and not truncated[:, :-1].any()
    assert not terminated.any()
    assert (rollout["next", "done"].squeeze(-1) == truncated).all()
    assert (rollout["next", "reward"] == 0).all()


def test_truncation_counts_steps_per_car_through_partial_resets():
    env = MountainCarContinuousEnv(batch_size=[4], seed=0, max_episode_steps=20)
    zero = torch.zeros(4, 1)
    td = env.reset()
    for _ in range(5):
        td = env.step(td.set("action", zero))["next"]
    before = td["observation"].clone()
    td["_reset"] = torch.tensor([[True], [False], [False], [True]])
    td = env.reset(td)
    assert (td["observation"][1:3] == before[1:3]).all()
    assert not torch.allclose(td["observation"][0], before[0]) and not torch.allclose(td["observation"][3], before[3])
    assert (td["observation"][[0, 3], 1] == 0).all()
    for _ in range(15):
        out = env.step(td.set("action", zero))
        td = out["next"]
    assert td["truncated"].squeeze(-1).tolist() == [False, True, True, False]
    assert (td["done"] == td["truncated"]).all()
    td = env.reset(td.set("_reset", td["done"]))
    for _ in range(5):
        td = env.step(td.set("action", zero))["next"]
    assert td["truncated"].squeeze(-1).tolist() == [True, False, False, True]


def test_collector_style_auto_reset():
    env = MountainCarContinuousEnv(batch_size=[2], seed=0, max_episode_steps=10)
    rollout = env.rollout(25, break_when_any_done=False)  # torchrl resets done cars in place
    done = rollout["next", "done"].squeeze(-1)
    assert done[:, 9].all() and done[:, 19].all() and done.sum() == 4
    assert (rollout[:, 10]["observation"][:, 1] == 0).all()  # a fresh start: at rest


def test_partial_steps_freeze_finished_cars():
    """``break_when_all_done`` steps only the cars still running; a finished car keeps its state and step count."""
    env = make_mountain_car_env(batch_size=[16], seed=3)
    policy = make_mountain_car_expert(power=0.3, tau=0.0)
    rollout = env.rollout(1000, policy, break_when_any_done=False, break_when_all_done=True)
    done = rollout["next", "done"].squeeze(-1)
    length = done.long().argmax(-1) + 1
    assert done.any(-1).all() and length.min() < length.max() == rollout.shape[1]
    assert (env._step_count.squeeze(-1) == length).all()
    returns = discounted_returns(rollout, 1.0)
    torch.testing.assert_close(returns, 100 - 0.1 * 0.3**2 * length.double(), atol=1e-4, rtol=0)


def test_seeded_and_reproducible():
    def roll(seed, **kw):
        torch.manual_seed(123)  # the random actions
        return MountainCarContinuousEnv(batch_size=[8], seed=seed, **kw).rollout(200)

    a, b, c = roll(3), roll(3), roll(4)
    assert (a["observation"] == b["observation"]).all() and (a["next", "reward"] == b["next", "reward"]).all()
    assert not torch.allclose(a["observation"][:, 0], c["observation"][:, 0])
    env = MountainCarContinuousEnv(batch_size=[8], seed=0)
    env.set_seed(3)
    torch.manual_seed(123)
    assert (env.rollout(200)["observation"] == a["observation"]).all()
    # initial states: U(-0.6, -0.4) at rest
    x0 = MountainCarContinuousEnv(batch_size=[10_000], seed=0).reset()["observation"]
    assert x0[:, 0].min() >= -0.6 and x0[:, 0].max() <= -0.4 and (x0[:, 1] == 0).all()
    assert abs(x0[:, 0].mean().item() + 0.5) < 0.003 and abs(x0[:, 0].std().item() - 0.2 / math.sqrt(12)) < 0.002


def test_expert_returns_match_gym():
    """The noisy expert's mean return: 100 batched episodes of ours against 20 of gym's.

    Returns have a standard deviation of about 0.15 (measured), so the two means differ by less than 4 standard
    errors of their difference unless the envs differ.
    """
    policy = make_mountain_car_expert()  # tau = 0.1: noisy
    torch.manual_seed(0)
    with set_exploration_type(ExplorationType.RANDOM):
        env = make_mountain_car_env(batch_size=[100], seed=0)
        ours = discounted_returns(env.rollout(1000, policy, break_when_any_done=False, break_when_all_done=True), 1.0)
        gym_env = make_mountain_car_gym_env()
        theirs = []
        for i in range(20):
            gym_env.set_seed(i)
            theirs.append(discounted_returns(gym_env.rollout(1000, policy), 1.0).item())
        gym_env.close()
    theirs = torch.tensor(theirs, dtype=torch.float64)
    se = math.sqrt(ours.var().item() / len(ours) + theirs.var().item() / len(theirs))
    assert 90 < ours.mean().item() < 96
    assert abs(ours.mean().item() - theirs.mean().item()) < 4 * se + 1e-3, (ours.mean(), theirs.mean(), se)


# ---------------------------------------------------------------------- construction
@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        ({"batch_size": -1}, ValueError, "batch_size must hold positive sizes"),
        ({"batch_size": [2, 0]}, ValueError, "batch_size must hold positive sizes"),
        ({"batch_size": 2.5}, TypeError, "batch_size must be an int or a sequence of ints"),
        ({"batch_size": "4"}, TypeError, "batch_size must be an int or a sequence of ints"),
        ({"max_episode_steps": 0}, ValueError, "max_episode_steps must be a positive integer"),
        ({"max_episode_steps": 99.5}, ValueError, "max_episode_steps must be a positive integer"),
        ({"seed": "0"}, TypeError, "seed must be an int or None"),
    ],
)
def test_bad_arguments(kwargs, error, match):
    with pytest.raises(error, match=match):
        MountainCarContinuousEnv(**kwargs)


def test_factories():
    env = make_mountain_car_env(seed=1)
    assert isinstance(env, MountainCarContinuousEnv) and env.batch_size == torch.Size([])
    assert make_mountain_car_env(batch_size=[5]).batch_size == torch.Size([5])
    assert make_mountain_car_env(batch_size=5).batch_size == torch.Size([5])
    gym_env = make_mountain_car_gym_env(seed=0)
    assert isinstance(gym_env, GymEnv) and gym_env.batch_size == torch.Size([])
    gym_env.close()
