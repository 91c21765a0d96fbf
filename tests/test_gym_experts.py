"""The gym datasets' hand-made experts (``torchrl_wbrm.policies.gym_experts``): known actions on chosen observations,
the MountainCar expert's noise drawn only from a generator it is given, and the swing-up reaching the top."""
from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from torchrl_wbrm.policies.gym_experts import (
    cartpole_expert_action,
    inverted_pendulum_expert_action,
    mountain_car_expert_action,
    pendulum_expert_action,
)


def test_known_actions():
    assert cartpole_expert_action(np.array([0.0, 0.0, 0.05, 0.0])) == 1
    assert cartpole_expert_action(np.array([[0.0, 0.0], [-0.05, 0.02]])) == 0  # any shape of its 4 numbers
    np.testing.assert_array_equal(mountain_car_expert_action(np.array([-0.5, 0.01])), np.float32([0.9]))
    np.testing.assert_array_equal(mountain_car_expert_action(np.array([-0.5, 0.0])), np.float32([-0.9]))
    np.testing.assert_array_equal(inverted_pendulum_expert_action(np.array([0.1, 0.02, 0.0, 0.0])), np.float32([0.3]))
    np.testing.assert_array_equal(inverted_pendulum_expert_action(np.array([0.0, 1.0, 0.0, 0.0])), np.float32([3.0]))
    # upright: the PD catch; hanging at rest: full torque to pump energy
    np.testing.assert_allclose(pendulum_expert_action(np.array([1.0, 0.0, 0.4])), np.float32([-1.0]), rtol=1e-6)
    assert abs(float(pendulum_expert_action(np.array([-1.0, 0.0, 0.0]))[0])) == 2.0


def test_the_mountain_car_noise_comes_from_the_generator_given():
    obs = np.array([-0.5, 0.01])
    rng, reference = np.random.default_rng(4), np.random.default_rng(4)
    noisy = [mountain_car_expert_action(obs, 0.05, rng) for _ in range(20)]
    expected = [np.clip(np.array([0.9 + 0.05 * reference.uniform(-1.0, 1.0)], dtype=np.float32), -1.0, 1.0)
                for _ in range(20)]
    np.testing.assert_array_equal(np.concatenate(noisy), np.concatenate(expected))
    assert len({float(a[0]) for a in noisy}) == 20
    with pytest.raises(ValueError, match="noise=0.3 needs an rng"):
        mountain_car_expert_action(obs, 0.3)


def test_the_pendulum_swing_up_reaches_the_top_and_stays():
    env = gym.make("Pendulum-v1")
    obs, _ = env.reset(seed=0)
    rewards = []
    for _ in range(200):
        obs, reward, *_ = env.step(pendulum_expert_action(obs))
        rewards.append(reward)
    assert sum(rewards) > -400 and obs[0] > 0.99  # random torques score about -1,180
