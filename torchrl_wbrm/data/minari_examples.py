"""Small Minari datasets on gymnasium classic-control envs, made locally: an expert heuristic
(:mod:`torchrl_wbrm.policies.gym_experts`) and a behaviour mix.

``MountainCarContinuous-v0`` (:func:`make_mountain_car_datasets`): the expert pushes along the velocity
(``0.9 sign(v) + 0.1 U(−1, 1)``, about +93.5 in about 80 steps); the behaviour is whole episodes of uniform random
actions (about −33 over the 999-step limit) and whole episodes of the expert with noise ``U(−1, 1)``.

``Pendulum-v1`` (:func:`make_pendulum_datasets`) (Box observation ``[cos θ, sin θ, θ̇]``, Box action ``[-2, 2]``, 200-step episodes):

* expert — an energy-pumping swing-up with a PD catch near the top
  (:func:`~torchrl_wbrm.policies.gym_experts.pendulum_expert_action`; about −140 per episode, against about −1,180 for
  uniform random torques), plus a little action noise;
* behaviour — whole episodes of uniform random torques, and whole episodes of the expert with more noise.

``CartPole-v1`` (:func:`make_cartpole_datasets`) (Box observation, ``Discrete(2)`` action, 500-step limit): the
expert pushes towards the pole's lean, ``1 if θ + 0.5 θ̇ > 0 else 0``
(:func:`~torchrl_wbrm.policies.gym_experts.cartpole_expert_action`; 500, the maximum, from every start tried), taking a uniform random action with probability 0.05; the behaviour is whole
episodes of uniform random actions (about 22) and whole episodes of the expert taking a random action with
probability 0.5 (about 170).

A multi-dimensional ``Box`` observation: :func:`register_reshaped_env` registers a gymnasium env whose observation
is another env's reshaped (gymnasium's ``ReshapeObservation``; ``CartPole-v1`` as ``(2, 2)``:
``torchrl_wbrm/CartPole_2x2-v1``), recorded in the dataset with an importable entry point
(:func:`make_reshaped_env`), so the evaluation env is recovered from the dataset alone; ``make_cartpole_datasets(...,
observation_shape=(2, 2))`` writes the CartPole datasets on it.

Written with :func:`~torchrl_wbrm.data.minari_data.write_minari_dataset` (``minari[hdf5]`` only), so
``env=minari`` can read them back; nothing is downloaded. Their ids are ``examples/<env>/expert-v0`` and
``examples/<env>/behaviour-v0`` (namespace ``examples/<env>``, ``--namespace`` to change it), apart from those of
``recipes/make_dataset.py format=minari`` (``make_dataset/<env>_seed<seed>/...``); ids that already exist are refused
before anything is collected::

    python -m torchrl_wbrm.data.minari_examples --env mountain_car --data-path datasets/minari  # or --env cartpole
    python recipes/wbrm_offline.py env=minari env.minari.expert=examples/mountain_car/expert-v0 \\
        env.minari.behaviour=examples/mountain_car/behaviour-v0 env.minari.data_path=datasets/minari q.bc_alpha=2.5
"""
from __future__ import annotations

import argparse
import os
from typing import Callable

import numpy as np

from torchrl_wbrm.data.minari_data import check_new_minari_ids, write_minari_dataset
from torchrl_wbrm.policies.gym_experts import cartpole_expert_action, mountain_car_expert_action, pendulum_expert_action

__all__ = [
    "collect_gym_episodes",
    "make_pendulum_datasets",
    "make_mountain_car_datasets",
    "make_cartpole_datasets",
    "make_reshaped_env",
    "register_reshaped_env",
    "PENDULUM",
    "MOUNTAIN_CAR",
    "CARTPOLE",
]

#: the examples' Minari namespaces are ``examples/<name>`` (``--namespace`` / ``namespace=`` to change)
NAMESPACE = "examples"

PENDULUM = "Pendulum-v1"
MOUNTAIN_CAR = "MountainCarContinuous-v0"
CARTPOLE = "CartPole-v1"


def make_reshaped_env(env_id: str, shape=None, action_shape=None, **kwargs):
    """``gymnasium.make(env_id, **kwargs)`` with its ``Box`` observation reshaped to ``shape``
    (``ReshapeObservation``) and, if given, its ``Box`` action to ``action_shape`` (the env takes an action of that
    shape and steps the original with it flattened, row-major)."""
    import gymnasium as gym
    from gymnasium.wrappers import ReshapeObservation

    env = gym.make(env_id, **kwargs)
    if shape is not None:
        env = ReshapeObservation(env, tuple(int(n) for n in shape))
    if action_shape is not None:
        box, action_shape = env.action_space, tuple(int(n) for n in action_shape)
        env = gym.wrappers.TransformAction(
            env, lambda a: np.asarray(a, dtype=box.dtype).reshape(box.shape),
            gym.spaces.Box(box.low.reshape(action_shape), box.high.reshape(action_shape), dtype=box.dtype))
    return env


def register_reshaped_env(env_id: str, shape=None, action_shape=None) -> str:
    """Register (once) the gymnasium env ``env_id`` with its observation reshaped to ``shape`` (and/or its ``Box``
    action to ``action_shape``); returns its id, ``torchrl_wbrm/<name>_<d1>x<d2>...-v<version>`` (``CartPole-v1``,
    ``(2, 2)`` -> ``torchrl_wbrm/CartPole_2x2-v1``; an action shape adds ``_a<d1>x<d2>...``).
    The spec's entry point is :func:`make_reshaped_env`, importable, so a dataset that records it can be evaluated
    in any process (``gymnasium.make`` of the recorded spec)."""
    import gymnasium as gym
    from gymnasium.envs.registration import parse_env_id

    if shape is None and action_shape is None:
        raise ValueError("register_reshaped_env: give an observation shape, an action shape or both.")
    shape = None if shape is None else tuple(int(n) for n in shape)
    action_shape = None if action_shape is None else tuple(int(n) for n in action_shape)
    _, name, version = parse_env_id(env_id)
    suffix = ("" if shape is None else "_" + "x".join(map(str, shape))) + (
        "" if action_shape is None else "_a" + "x".join(map(str, action_shape)))
    new_id = f"torchrl_wbrm/{name}{suffix}" + ("" if version is None else f"-v{version}")
    if new_id not in gym.registry:
        gym.register(new_id, entry_point=f"{__name__}:make_reshaped_env",
                     max_episode_steps=gym.spec(env_id).max_episode_steps,
                     kwargs={"env_id": env_id, "shape": None if shape is None else list(shape),
                             "action_shape": None if action_shape is None else list(action_shape)})
    return new_id


def collect_gym_episodes(env_id: str, policy: Callable[[np.ndarray, np.random.Generator], np.ndarray], episodes: int,
                         *, seed: int) -> list[dict]:
    """``episodes`` whole episodes of ``policy(observation, rng)`` in ``gymnasium.make(env_id)``, episode ``i`` reset
    with ``seed + i``: the episode dicts of :func:`~torchrl_wbrm.data.minari_data.write_minari_dataset`."""
    import gymnasium as gym

    env = gym.make(env_id)
    rng = np.random.default_rng(seed)
    out = []
    for i in range(episodes):
        obs, _ = env.reset(seed=seed + i)
        observations, actions, rewards, terminations, truncations = [obs], [], [], [], []
        done = False
        while not done:
            action = policy(obs, rng)
            obs, reward, terminated, truncated, _ = env.step(action)
            observations.append(obs)
            actions.append(action)
            rewards.append(reward)
            terminations.append(terminated)
            truncations.append(truncated)
            done = terminated or truncated
        out.append({"observations": np.stack(observations), "actions": np.stack(actions),
                    "rewards": np.asarray(rewards, dtype=np.float64), "terminations": np.asarray(terminations),
                    "truncations": np.asarray(truncations)})
    env.close()
    return out


def _new_ids(namespace: str, data_path) -> dict:
    """``<namespace>/expert-v0`` and ``<namespace>/behaviour-v0``, refused (before any collecting) if either exists
    under ``data_path``."""
    ids = {"expert": f"{namespace}/expert-v0", "behaviour": f"{namespace}/behaviour-v0"}
    check_new_minari_ids(ids.values(), data_path, setting=f"--namespace (now {namespace!r})")
    return ids


def _noisy_expert(std: float):
    def policy(obs, rng):
        return np.clip(pendulum_expert_action(obs) + rng.normal(0.0, std, 1).astype(np.float32), -2.0, 2.0)

    return policy


def _uniform(obs, rng):
    return rng.uniform(-2.0, 2.0, 1).astype(np.float32)


def make_pendulum_datasets(data_path: str | os.PathLike, *, expert_episodes: int = 20, random_episodes: int = 40,
                           noisy_expert_episodes: int = 20, seed: int = 0, namespace: str = f"{NAMESPACE}/pendulum") -> dict:
    """Write ``<namespace>/expert-v0`` and ``<namespace>/behaviour-v0`` under ``data_path``; returns their ids and
    paths. Expert: the heuristic with action noise 0.1; behaviour: ``random_episodes`` of uniform torques, then
    ``noisy_expert_episodes`` of the heuristic with noise 1.0 (other seeds than the expert's)."""
    ids = _new_ids(namespace, data_path)
    expert = collect_gym_episodes(PENDULUM, _noisy_expert(0.1), expert_episodes, seed=seed)
    behaviour = collect_gym_episodes(PENDULUM, _uniform, random_episodes, seed=seed + 10_000)
    behaviour += collect_gym_episodes(PENDULUM, _noisy_expert(1.0), noisy_expert_episodes, seed=seed + 20_000)
    write_minari_dataset(ids["expert"], expert, data_path=data_path, env=PENDULUM, eval_env=PENDULUM,
                         algorithm_name="swing-up heuristic, action noise 0.1",
                         description="torchrl_wbrm example: Pendulum-v1 expert")
    write_minari_dataset(ids["behaviour"], behaviour, data_path=data_path, env=PENDULUM, eval_env=PENDULUM,
                         algorithm_name="uniform random torques, then the heuristic with action noise 1.0",
                         description="torchrl_wbrm example: Pendulum-v1 behaviour")
    return {**ids, **{f"{k}_path": os.path.join(os.fspath(data_path), v) for k, v in ids.items()}}


def make_mountain_car_datasets(data_path: str | os.PathLike, *, expert_episodes: int = 20, random_episodes: int = 6,
                               noisy_expert_episodes: int = 30, seed: int = 0,
                               namespace: str = f"{NAMESPACE}/mountain_car") -> dict:
    """Write ``<namespace>/expert-v0`` (the expert, noise 0.1) and ``<namespace>/behaviour-v0``
    (``random_episodes`` of uniform actions, then ``noisy_expert_episodes`` of the expert with noise 1) under
    ``data_path``; returns their ids and paths."""
    def expert(noise):
        return lambda obs, rng: mountain_car_expert_action(obs, noise, rng)

    def uniform(obs, rng):
        return rng.uniform(-1.0, 1.0, 1).astype(np.float32)

    ids = _new_ids(namespace, data_path)
    ex = collect_gym_episodes(MOUNTAIN_CAR, expert(0.1), expert_episodes, seed=seed)
    behaviour = collect_gym_episodes(MOUNTAIN_CAR, uniform, random_episodes, seed=seed + 10_000)
    behaviour += collect_gym_episodes(MOUNTAIN_CAR, expert(1.0), noisy_expert_episodes, seed=seed + 20_000)
    write_minari_dataset(ids["expert"], ex, data_path=data_path, env=MOUNTAIN_CAR, eval_env=MOUNTAIN_CAR,
                         algorithm_name="0.9 sign(v) + 0.1 U(-1, 1)",
                         description="torchrl_wbrm example: MountainCarContinuous-v0 expert")
    write_minari_dataset(ids["behaviour"], behaviour, data_path=data_path, env=MOUNTAIN_CAR, eval_env=MOUNTAIN_CAR,
                         algorithm_name="uniform random actions, then 0.9 sign(v) + U(-1, 1)",
                         description="torchrl_wbrm example: MountainCarContinuous-v0 behaviour")
    return {**ids, **{f"{k}_path": os.path.join(os.fspath(data_path), v) for k, v in ids.items()}}


def make_cartpole_datasets(data_path: str | os.PathLike, *, expert_episodes: int = 10, random_episodes: int = 20,
                           noisy_expert_episodes: int = 20, noise: float = 0.5, seed: int = 0,
                           observation_shape=None, namespace: str = f"{NAMESPACE}/cartpole") -> dict:
    """Write ``<namespace>/expert-v0`` (the expert, a random action with probability 0.05) and
    ``<namespace>/behaviour-v0`` (``random_episodes`` of uniform actions, then ``noisy_expert_episodes`` of the expert
    taking a random action with probability ``noise``) on ``CartPole-v1`` (a ``Discrete(2)`` action) under
    ``data_path``; with ``observation_shape`` on CartPole with that observation shape (:func:`register_reshaped_env`).
    Returns their ids and paths and the env's id."""
    env_id = CARTPOLE if observation_shape is None else register_reshaped_env(CARTPOLE, observation_shape)

    def expert(epsilon):
        def policy(obs, rng):
            return int(rng.integers(0, 2)) if rng.random() < epsilon else cartpole_expert_action(obs)

        return policy

    ids = _new_ids(namespace, data_path)
    ex = collect_gym_episodes(env_id, expert(0.05), expert_episodes, seed=seed)
    behaviour = collect_gym_episodes(env_id, expert(1.0), random_episodes, seed=seed + 10_000)
    behaviour += collect_gym_episodes(env_id, expert(noise), noisy_expert_episodes, seed=seed + 20_000)
    write_minari_dataset(ids["expert"], ex, data_path=data_path, env=env_id, eval_env=env_id,
                         algorithm_name="1 if θ + 0.5 θ' > 0 else 0; a random action with probability 0.05",
                         description=f"torchrl_wbrm example: {env_id} expert")
    write_minari_dataset(ids["behaviour"], behaviour, data_path=data_path, env=env_id, eval_env=env_id,
                         algorithm_name=f"uniform random actions, then the expert with random actions at {noise}",
                         description=f"torchrl_wbrm example: {env_id} behaviour")
    return {**ids, "env": env_id,
            **{f"{k}_path": os.path.join(os.fspath(data_path), v) for k, v in ids.items()}}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--env", choices=("mountain_car", "pendulum", "cartpole"), default="mountain_car")
    parser.add_argument("--data-path", default="datasets/minari", help="Minari data path to write under")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--namespace", default=None,
                        help=f"Minari namespace of the two datasets (default: {NAMESPACE}/<env>); existing ids are "
                             f"refused before anything is collected")
    args = parser.parse_args(argv)
    make = {"mountain_car": make_mountain_car_datasets, "pendulum": make_pendulum_datasets,
            "cartpole": make_cartpole_datasets}[args.env]
    try:
        out = make(args.data_path, seed=args.seed, namespace=args.namespace or f"{NAMESPACE}/{args.env}")
    except (FileExistsError, ValueError) as err:
        raise SystemExit(f"minari_examples: {err}") from None
    print(f"expert:    {out['expert_path']}\nbehaviour: {out['behaviour_path']}")


if __name__ == "__main__":
    main()
