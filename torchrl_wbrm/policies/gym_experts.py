"""The hand-made experts of the gymnasium datasets made here: each maps one observation (a NumPy array) to an action.

The example datasets (:mod:`torchrl_wbrm.data.minari_examples`) and the benchmark (:mod:`torchrl_wbrm.data.benchmark`)
add their own noise around them. None needs training or a download:

* ``Pendulum-v1``: an energy-pumping swing-up with a PD catch near the top (:func:`pendulum_expert_action`);
* ``MountainCarContinuous-v0``: push along the velocity, ``0.9 sign(v)`` (:func:`mountain_car_expert_action`);
* ``CartPole-v1``: push towards the pole's lean, ``θ + 0.5 θ' > 0`` (:func:`cartpole_expert_action`);
* ``LunarLanderContinuous-v3``: gymnasium's own ``heuristic`` controller (:func:`lunar_lander_expert_action`);
* ``InvertedPendulum-v5``: a PD controller on the cart and the pole (:func:`inverted_pendulum_expert_action`).

    >>> import numpy as np
    >>> cartpole_expert_action(np.array([0.0, 0.0, 0.05, 0.0]))
    1
    >>> mountain_car_expert_action(np.array([-0.5, -0.01]))
    array([-0.9], dtype=float32)
"""
from __future__ import annotations

import numpy as np

__all__ = [
    "INVERTED_PENDULUM_GAINS",
    "cartpole_expert_action",
    "inverted_pendulum_expert_action",
    "lunar_lander_expert_action",
    "mountain_car_expert_action",
    "pendulum_expert_action",
]


def pendulum_expert_action(observation: np.ndarray) -> np.ndarray:
    """Swing-up heuristic for ``Pendulum-v1``: pump energy ``½θ̇² + 15 cos θ`` towards the upright's 15 at full
    torque, and catch with ``−(12θ + 2.5θ̇)`` once ``cos θ > 0.85``."""
    c, s, w = (float(v) for v in np.asarray(observation).reshape(-1)[:3])
    theta = np.arctan2(s, c)
    if c > 0.85:
        u = -(12.0 * theta + 2.5 * w)
    else:
        u = 2.0 * np.sign((15.0 - (0.5 * w * w + 15.0 * c)) * w + 1e-6)
    return np.clip(np.array([u], dtype=np.float32), -2.0, 2.0)


def mountain_car_expert_action(observation: np.ndarray, noise: float = 0.0,
                               rng: np.random.Generator | None = None) -> np.ndarray:
    """``clip(0.9 sign(v) + noise U(−1, 1), −1, 1)`` for ``MountainCarContinuous-v0`` (left at rest). Without
    ``rng`` it is the noiseless ``0.9 sign(v)`` and draws nothing; with it, one uniform number per call."""
    direction = 1.0 if float(np.asarray(observation).reshape(-1)[1]) > 0 else -1.0
    if rng is None:
        if noise:
            raise ValueError(f"mountain_car_expert_action: noise={noise!r} needs an rng to draw it from.")
        return np.array([0.9 * direction], dtype=np.float32)
    return np.clip(np.array([0.9 * direction + noise * rng.uniform(-1.0, 1.0)], dtype=np.float32), -1.0, 1.0)


def cartpole_expert_action(observation: np.ndarray) -> int:
    """``1`` (push right) if ``θ + 0.5 θ̇ > 0``, else ``0``, for ``CartPole-v1`` (any shape of its 4 numbers)."""
    _, _, theta, omega = (float(v) for v in np.asarray(observation).reshape(-1)[:4])
    return int(theta + 0.5 * omega > 0)


def lunar_lander_expert_action(observation: np.ndarray) -> np.ndarray:
    """gymnasium's own ``heuristic`` for the continuous lunar lander (main engine, then the lateral engines); needs
    ``box2d``."""
    from types import SimpleNamespace

    from gymnasium.envs.box2d.lunar_lander import heuristic

    env = SimpleNamespace(unwrapped=SimpleNamespace(continuous=True))
    return np.asarray(heuristic(env, np.asarray(observation, dtype=np.float64)), dtype=np.float32)


#: the PD gains of :func:`inverted_pendulum_expert_action` on ``[x, θ, ẋ, θ̇]``
INVERTED_PENDULUM_GAINS = np.array([1.0, 10.0, 1.0, 1.0])


def inverted_pendulum_expert_action(observation: np.ndarray) -> np.ndarray:
    """A PD controller for ``InvertedPendulum-v5``: force ``k · [x, θ, ẋ, θ̇]`` with ``k = (1, 10, 1, 1)``, which
    holds the pole for the full 1000 steps from every start tried, clipped to ``[−3, 3]``."""
    force = float(INVERTED_PENDULUM_GAINS @ np.asarray(observation, dtype=np.float64).reshape(-1)[:4])
    return np.clip(np.array([force], dtype=np.float32), -3.0, 3.0)
