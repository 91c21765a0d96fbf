"""A benchmark of offline datasets made here, in Minari format: standard gymnasium tasks, each with an expert and a
behaviour dataset, and the returns of random actions and of the expert as the datasets' reference scores.

Nothing is downloaded: every expert is a hand-made controller (:mod:`torchrl_wbrm.policies.gym_experts`). Every
task is built the same way:

* **expert** (``<namespace>/<task>/expert-v0``): the controller with Gaussian action noise of standard deviation
  ``0.05 × (high − low)`` (5% of the action range), clipped to the action box;
* **behaviour** (``<namespace>/<task>/behaviour-v0``): whole episodes of uniform random actions, with every fifth
  episode the expert's (the same noisy controller, other reset seeds);
* **reference scores** (Minari's ``ref_min_score`` / ``ref_max_score``, as D4RL defines them): the mean return of
  uniform random actions and of the noisy expert over ``reference_episodes`` fresh episodes. A return ``R`` scores
  ``100 (R − ref_min) / (ref_max − ref_min)``: 0 is random actions, 100 the expert
  (:func:`normalised_score`).

The tasks (:data:`BENCHMARK_TASKS`) differ in horizon, reward scale and termination:

============================ ============= ================= ====================================================
task                         episode       terminations      expert
============================ ============= ================= ====================================================
``Pendulum-v1``              200 steps     none              energy-pumping swing-up with a PD catch
``MountainCarContinuous-v0`` ≤ 999 steps   at the goal       push along the velocity, ``0.9 sign(v)``
``LunarLanderContinuous-v3`` ≤ 1000 steps  landing or crash  gymnasium's own ``heuristic`` controller
``InvertedPendulum-v5``      ≤ 1000 steps  the pole falls    a PD controller on the cart and the pole
============================ ============= ================= ====================================================

``LunarLanderContinuous-v3`` needs ``box2d`` and ``InvertedPendulum-v5`` needs ``mujoco`` (the ``benchmark`` extra:
``pip install -e ".[benchmark]"``).

One command writes every dataset (tasks whose simulator is missing are refused by name)::

    python -m torchrl_wbrm.data.benchmark --data-path datasets/benchmark
    python recipes/wbrm_offline.py env=minari env.minari.data_path=datasets/benchmark \\
        env.minari.expert=benchmark/pendulum/expert-v0 env.minari.behaviour=benchmark/pendulum/behaviour-v0
"""
from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from typing import Callable

import numpy as np

from torchrl_wbrm.data.minari_data import minari_data_root, write_minari_dataset
from torchrl_wbrm.data.minari_examples import collect_gym_episodes
from torchrl_wbrm.policies.gym_experts import (
    inverted_pendulum_expert_action,
    lunar_lander_expert_action,
    mountain_car_expert_action,
    pendulum_expert_action,
)

__all__ = [
    "BENCHMARK_TASKS",
    "BenchmarkTask",
    "benchmark_ids",
    "make_benchmark",
    "make_benchmark_task",
    "normalised_score",
]

#: the Minari namespace of the benchmark's datasets
NAMESPACE = "benchmark"


@dataclass(frozen=True)
class BenchmarkTask:
    """One benchmark task: a gymnasium env, its hand-made expert and the datasets' sizes.

    Attributes:
        name: short name, the dataset ids' middle part (``benchmark/<name>/expert-v0``).
        env_id: the gymnasium id (recorded in the datasets: the evaluation env).
        expert: the noiseless controller, ``observation -> action``.
        expert_episodes: episodes of the expert dataset.
        behaviour_episodes: episodes of the behaviour dataset (every fifth the expert's, the rest random).
        expert_description: how the controller acts, recorded as the datasets' ``algorithm_name``.
        requires: the PyPI package the simulator needs (``None``: gymnasium alone).
    """

    name: str
    env_id: str
    expert: Callable[[np.ndarray], np.ndarray]
    expert_episodes: int
    behaviour_episodes: int
    expert_description: str
    requires: str | None = None


BENCHMARK_TASKS: dict[str, BenchmarkTask] = {
    task.name: task for task in (
        BenchmarkTask("pendulum", "Pendulum-v1", pendulum_expert_action, 100, 300,
                      "energy-pumping swing-up with a PD catch near the top"),
        BenchmarkTask("mountain_car", "MountainCarContinuous-v0", mountain_car_expert_action, 100, 100,
                      "0.9 sign(velocity)"),
        BenchmarkTask("lunar_lander", "LunarLanderContinuous-v3", lunar_lander_expert_action, 100, 300,
                      "gymnasium's lunar_lander.heuristic (continuous)", requires="box2d"),
        BenchmarkTask("inverted_pendulum", "InvertedPendulum-v5", inverted_pendulum_expert_action, 20, 300,
                      "PD force (1, 10, 1, 1) . [x, theta, x', theta']", requires="mujoco"),
    )
}

#: every fifth behaviour episode is the expert's
EXPERT_EVERY = 5


def normalised_score(returns, ref_min: float, ref_max: float):
    """D4RL's normalised score, ``100 (R − ref_min) / (ref_max − ref_min)``: 0 is random actions, 100 the expert."""
    if not ref_max > ref_min:
        raise ValueError(f"normalised_score needs ref_max > ref_min, got ref_min={ref_min!r}, ref_max={ref_max!r}.")
    return 100.0 * (np.asarray(returns, dtype=np.float64) - ref_min) / (ref_max - ref_min)


def benchmark_ids(name: str, namespace: str = NAMESPACE) -> dict[str, str]:
    """The two dataset ids of task ``name``: ``{"expert": "<ns>/<name>/expert-v0", "behaviour": ...}``."""
    return {kind: f"{namespace}/{name}/{kind}-v0" for kind in ("expert", "behaviour")}


def _policies(task: BenchmarkTask, space):
    low, high = np.asarray(space.low, dtype=np.float32), np.asarray(space.high, dtype=np.float32)
    std = 0.05 * (high - low)

    def expert(obs, rng):
        return np.clip(task.expert(obs) + rng.normal(0.0, 1.0, low.shape).astype(np.float32) * std, low, high)

    def uniform(obs, rng):
        return rng.uniform(low, high).astype(np.float32)

    return expert, uniform


def _returns(episodes: list[dict]) -> np.ndarray:
    return np.array([float(np.sum(ep["rewards"])) for ep in episodes])


def _check_simulator(task: BenchmarkTask) -> None:
    if task.requires is None:
        return
    import importlib.util

    module = {"box2d": "Box2D", "mujoco": "mujoco"}[task.requires]
    if importlib.util.find_spec(module) is None:
        raise ModuleNotFoundError(
            f"Benchmark task {task.name!r} ({task.env_id}) needs the {task.requires!r} package: "
            f"pip install -e \".[benchmark]\" (or leave it out with --tasks)."
        )


def make_benchmark_task(task: BenchmarkTask | str, data_path: str | os.PathLike, *, seed: int = 0,
                        reference_episodes: int = 100, namespace: str = NAMESPACE,
                        expert_episodes: int | None = None, behaviour_episodes: int | None = None,
                        overwrite: bool = False) -> dict:
    """Write one task's expert and behaviour datasets under ``data_path``; returns the ids, paths and the returns
    (random, behaviour, expert, and the reference scores).

    Episode ``i`` of each collection is reset with its own seed (expert ``seed + i``, behaviour
    ``seed + 10_000 + i``, the references ``seed + 20_000 + i`` and ``seed + 30_000 + i``), so the same seed gives
    the same datasets. An existing dataset id is refused before anything is collected unless ``overwrite``.
    """
    import gymnasium as gym

    task = BENCHMARK_TASKS[task] if isinstance(task, str) else task
    _check_simulator(task)
    ids = benchmark_ids(task.name, namespace)
    root = minari_data_root(data_path)
    for kind, dataset_id in ids.items():
        path = root / dataset_id
        if path.exists():
            if not overwrite:
                raise FileExistsError(f"The Minari dataset {dataset_id!r} already exists at {path}: pass "
                                      f"--overwrite to replace it, or another --data-path / --namespace.")
            import shutil

            shutil.rmtree(path)
    env = gym.make(task.env_id)
    expert, uniform = _policies(task, env.action_space)
    env.close()
    n_expert = task.expert_episodes if expert_episodes is None else int(expert_episodes)
    n_behaviour = task.behaviour_episodes if behaviour_episodes is None else int(behaviour_episodes)
    if n_expert < 1 or n_behaviour < EXPERT_EVERY:
        raise ValueError(f"make_benchmark_task: expert_episodes must be >= 1 and behaviour_episodes >= "
                         f"{EXPERT_EVERY}, got {n_expert} and {n_behaviour}.")

    expert_data = collect_gym_episodes(task.env_id, expert, n_expert, seed=seed)
    behaviour = []
    for i in range(n_behaviour):  # one episode at a time: every fifth the expert's, the rest uniform random
        policy = expert if i % EXPERT_EVERY == EXPERT_EVERY - 1 else uniform
        behaviour += collect_gym_episodes(task.env_id, policy, 1, seed=seed + 10_000 + i)
    random_ref = collect_gym_episodes(task.env_id, uniform, reference_episodes, seed=seed + 20_000)
    expert_ref = collect_gym_episodes(task.env_id, expert, reference_episodes, seed=seed + 30_000)
    ref_min, ref_max = float(_returns(random_ref).mean()), float(_returns(expert_ref).mean())

    noise = "Gaussian action noise, std 5% of the action range"
    common = dict(data_path=data_path, env=task.env_id, eval_env=task.env_id, ref_min_score=ref_min,
                  ref_max_score=ref_max, num_episodes_average_score=reference_episodes)
    write_minari_dataset(ids["expert"], expert_data, algorithm_name=f"{task.expert_description}; {noise}",
                         description=f"torchrl_wbrm benchmark: {task.env_id} expert, {n_expert} episodes", **common)
    write_minari_dataset(
        ids["behaviour"], behaviour,
        algorithm_name=f"uniform random actions; every {EXPERT_EVERY}th episode the expert ({noise})",
        description=f"torchrl_wbrm benchmark: {task.env_id} behaviour, {n_behaviour} episodes", **common)
    returns = {"random": _returns(random_ref), "behaviour": _returns(behaviour), "expert": _returns(expert_data)}
    return {
        "task": task.name, "env_id": task.env_id, **ids,
        **{f"{kind}_path": str(root / dataset_id) for kind, dataset_id in ids.items()},
        "ref_min_score": ref_min, "ref_max_score": ref_max,
        **{f"{k}_return_mean": float(v.mean()) for k, v in returns.items()},
        **{f"{k}_return_std": float(v.std()) for k, v in returns.items()},
        "expert_transitions": int(sum(len(ep["rewards"]) for ep in expert_data)),
        "behaviour_transitions": int(sum(len(ep["rewards"]) for ep in behaviour)),
        "expert_episodes": n_expert, "behaviour_episodes": n_behaviour,
        "behaviour_normalised": float(normalised_score(returns["behaviour"].mean(), ref_min, ref_max)),
    }


def make_benchmark(data_path: str | os.PathLike, *, tasks=None, seed: int = 0, **kwargs) -> list[dict]:
    """:func:`make_benchmark_task` for each of ``tasks`` (default: every task of :data:`BENCHMARK_TASKS`)."""
    names = list(BENCHMARK_TASKS) if tasks is None else list(tasks)
    for name in names:
        if name not in BENCHMARK_TASKS:
            raise ValueError(f"Unknown benchmark task {name!r}: choose from {list(BENCHMARK_TASKS)}.")
        _check_simulator(BENCHMARK_TASKS[name])  # every missing simulator before any collecting
    return [make_benchmark_task(name, data_path, seed=seed, **kwargs) for name in names]


def benchmark_table(rows: list[dict]) -> str:
    """The benchmark's datasets as a Markdown table: returns of random actions, the behaviour data and the expert
    (mean ± std over episodes), the behaviour's normalised score and the sizes."""
    lines = ["| task | env | random actions | behaviour data | expert data | behaviour, normalised | "
             "transitions (expert / behaviour) |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['task']} | {r['env_id']} | {r['random_return_mean']:.1f} ± {r['random_return_std']:.1f} | "
            f"{r['behaviour_return_mean']:.1f} ± {r['behaviour_return_std']:.1f} | "
            f"{r['expert_return_mean']:.1f} ± {r['expert_return_std']:.1f} | {r['behaviour_normalised']:.1f} | "
            f"{r['expert_transitions']:,} / {r['behaviour_transitions']:,} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Write the torchrl_wbrm benchmark's Minari datasets.")
    parser.add_argument("--data-path", default="datasets/benchmark", help="Minari data path to write under")
    parser.add_argument("--tasks", nargs="+", default=None, choices=list(BENCHMARK_TASKS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--reference-episodes", type=int, default=100)
    parser.add_argument("--namespace", default=NAMESPACE)
    parser.add_argument("--overwrite", action="store_true", help="replace datasets that already exist")
    args = parser.parse_args(argv)
    rows = make_benchmark(args.data_path, tasks=args.tasks, seed=args.seed, overwrite=args.overwrite,
                          reference_episodes=args.reference_episodes, namespace=args.namespace)
    print(benchmark_table(rows))
    for r in rows:
        print(f"{r['task']}: env.minari.data_path={args.data_path} env.minari.expert={r['expert']} "
              f"env.minari.behaviour={r['behaviour']}")


if __name__ == "__main__":
    main()
