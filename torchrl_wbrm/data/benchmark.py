"""A benchmark of offline datasets made here, in Minari format: standard gymnasium tasks, each with an expert and a
behaviour dataset, and the returns of random actions and of the expert as the datasets' reference scores.

Nothing is downloaded: every expert is a hand-made controller (:mod:`torchrl_wbrm.policies.gym_experts`). Every
task is built the same way:

* **expert** (``<namespace>/<task>/expert-v0``): the controller with Gaussian action noise of standard deviation
  ``0.05 × (high − low)`` (5% of the action range), clipped to the action box;
* **behaviour** (``<namespace>/<task>/behaviour-v0``): whole episodes of uniform random actions, with every fifth
  episode the expert's (the same noisy controller, other reset seeds);
* **the few-demonstration axis**: an expert *pool* (``expert-pool-v0``, twice the expert dataset's episodes, fresh
  reset seeds) from which a run draws its few expert episodes by its own seed (``env.minari.expert_episodes``, see
  :class:`~torchrl_wbrm.data.minari_data.MinariDataConfig`), and behaviour sets of the behaviour dataset's size in
  which 5%, 10% and 20% of the episodes are the expert's and the rest uniform random (``behaviour-expert05-v0``,
  ``behaviour-expert10-v0``, ``behaviour-expert20-v0``; :func:`expert_episode_indices` says which), plus
  ``medium-v0``, where every step takes the expert's action with probability ½ and a uniform random one otherwise;
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

A few-demonstration run: three expert episodes drawn from the pool by the run's seed, and the behaviour set that
hides 10% expert episodes among random ones::

    python recipes/wbrm_offline.py env=minari env.minari.data_path=datasets/benchmark \\
        env.minari.expert=benchmark/pendulum/expert-pool-v0 env.minari.expert_episodes=3 \\
        env.minari.behaviour=benchmark/pendulum/behaviour-expert10-v0
"""
from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass
from typing import Callable

import numpy as np

from torchrl_wbrm.data.locomotion import (
    DEFAULT_EXPERT_SHARES,
    DEFAULT_TRANSITIONS,
    LOCOMOTION_DATASETS,
    check_locomotion_ids,
    locomotion_table,
    make_locomotion_task,
)
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
    "EXPERT_SHARES",
    "MEDIUM_EXPERT_PROBABILITY",
    "benchmark_ids",
    "benchmark_table",
    "check_benchmark_ids",
    "expert_episode_indices",
    "few_demonstration_ids",
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

#: the few-demonstration behaviour sets: ``behaviour-expert<pp>-v0`` -> the share of its episodes that are the expert's
EXPERT_SHARES = {"behaviour-expert05-v0": 0.05, "behaviour-expert10-v0": 0.10, "behaviour-expert20-v0": 0.20}

#: ``medium-v0``: the probability that a step takes the expert's action (else a uniform random one)
MEDIUM_EXPERT_PROBABILITY = 0.5

#: the expert pool: this many times the expert dataset's episodes, from fresh reset seeds
POOL_FACTOR = 2


def normalised_score(returns, ref_min: float, ref_max: float):
    """D4RL's normalised score, ``100 (R − ref_min) / (ref_max − ref_min)``: 0 is random actions, 100 the expert."""
    if not ref_max > ref_min:
        raise ValueError(f"normalised_score needs ref_max > ref_min, got ref_min={ref_min!r}, ref_max={ref_max!r}.")
    return 100.0 * (np.asarray(returns, dtype=np.float64) - ref_min) / (ref_max - ref_min)


def benchmark_ids(name: str, namespace: str = NAMESPACE) -> dict[str, str]:
    """The two dataset ids of task ``name``: ``{"expert": "<ns>/<name>/expert-v0", "behaviour": ...}``."""
    return {kind: f"{namespace}/{name}/{kind}-v0" for kind in ("expert", "behaviour")}


def few_demonstration_ids(name: str, namespace: str = NAMESPACE) -> dict[str, str]:
    """The few-demonstration dataset ids of task ``name``: ``{"expert_pool": "<ns>/<name>/expert-pool-v0",
    "behaviour_expert05": ..., "behaviour_expert10": ..., "behaviour_expert20": ..., "medium": ...}``."""
    ids = {"expert_pool": f"{namespace}/{name}/expert-pool-v0"}
    for dataset_name in EXPERT_SHARES:
        ids[dataset_name[:-3].replace("-", "_")] = f"{namespace}/{name}/{dataset_name}"
    ids["medium"] = f"{namespace}/{name}/medium-v0"
    return ids


def expert_episode_indices(episodes: int, share: float) -> list[int]:
    """Which episodes of a ``behaviour-expert<pp>-v0`` set of ``episodes`` episodes are the expert's:
    ``k = max(1, round(share × episodes))`` of them, evenly spread (episode ``⌊(j + 1) episodes / k⌋ − 1`` for
    ``j < k``); the others are uniform random actions. With 300 episodes: every 20th, 10th and 5th episode for 5%,
    10% and 20% (the 20% set then holds the episodes of ``behaviour-v0``).

        >>> expert_episode_indices(20, 0.10)
        [9, 19]
        >>> expert_episode_indices(300, 0.05)[:3]
        [19, 39, 59]
    """
    if episodes < 1 or not 0.0 < share <= 1.0:
        raise ValueError(f"expert_episode_indices needs episodes >= 1 and 0 < share <= 1, got {episodes}, {share}.")
    k = min(episodes, max(1, round(share * episodes)))
    return [(j + 1) * episodes // k - 1 for j in range(k)]


def _expert_ids(ids) -> dict:
    """A dataset's ``metadata.json`` entry naming its expert episodes (Minari ids; ``baselines.bc.data=oracle``)."""
    return {"expert_episode_ids": sorted(int(i) for i in ids)}


def _policies(task: BenchmarkTask, space):
    low, high = np.asarray(space.low, dtype=np.float32), np.asarray(space.high, dtype=np.float32)
    std = 0.05 * (high - low)

    def expert(obs, rng):
        return np.clip(task.expert(obs) + rng.normal(0.0, 1.0, low.shape).astype(np.float32) * std, low, high)

    def uniform(obs, rng):
        return rng.uniform(low, high).astype(np.float32)

    return expert, uniform


def _medium(expert, uniform, counter: list):
    """The expert's action with probability :data:`MEDIUM_EXPERT_PROBABILITY`, else a uniform one; ``counter[0]``
    counts the expert's steps."""

    def policy(obs, rng):
        if rng.random() < MEDIUM_EXPERT_PROBABILITY:
            counter[0] += 1
            return expert(obs, rng)
        return uniform(obs, rng)

    return policy


def _steps(episodes: list[dict]) -> int:
    return int(sum(len(ep["rewards"]) for ep in episodes))


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
                        pool_episodes: int | None = None, few_demonstrations: bool = True,
                        overwrite: bool = False) -> dict:
    """Write one task's datasets under ``data_path``; returns the ids, paths, the returns (random, behaviour,
    expert, and the reference scores) and, under ``"datasets"``, each dataset's make-up (:func:`benchmark_table`).

    Episode ``i`` of each collection is reset with its own seed (expert ``seed + i``, behaviour
    ``seed + 10_000 + i``, the references ``seed + 20_000 + i`` and ``seed + 30_000 + i``), so the same seed gives
    the same datasets. With ``few_demonstrations`` (the default) the few-demonstration sets are written too
    (:func:`few_demonstration_ids`): the expert pool of ``pool_episodes`` episodes (default :data:`POOL_FACTOR`
    times the expert dataset's) reset with ``seed + 40_000 + i``, and the ``behaviour-expert<pp>-v0`` and
    ``medium-v0`` sets of the behaviour dataset's size, whose episode ``i`` is reset with ``seed + 10_000 + i``
    as the behaviour dataset's (an expert or a uniform episode of one reset seed is the same episode in every set).
    ``expert-v0`` and ``behaviour-v0`` do not depend on them. An existing dataset id is refused before anything is
    collected unless ``overwrite``.
    """
    import gymnasium as gym

    import shutil

    task = BENCHMARK_TASKS[task] if isinstance(task, str) else task
    _check_simulator(task)
    ids = benchmark_ids(task.name, namespace)
    extra_ids = few_demonstration_ids(task.name, namespace) if few_demonstrations else {}
    root = minari_data_root(data_path)
    # every id checked (syntax, inside the data path, new unless overwrite) before anything is removed or written
    folders = check_benchmark_ids([task.name], data_path, namespace=namespace,
                                  few_demonstrations=few_demonstrations, overwrite=overwrite)
    for path in folders:
        if path.exists():  # overwrite: the old dataset, inside the data path (checked above)
            shutil.rmtree(path)
    env = gym.make(task.env_id)
    expert, uniform = _policies(task, env.action_space)
    env.close()
    n_expert = task.expert_episodes if expert_episodes is None else int(expert_episodes)
    n_behaviour = task.behaviour_episodes if behaviour_episodes is None else int(behaviour_episodes)
    n_pool = POOL_FACTOR * n_expert if pool_episodes is None else int(pool_episodes)
    if n_expert < 1 or n_behaviour < EXPERT_EVERY or n_pool < 1:
        raise ValueError(f"make_benchmark_task: expert_episodes and pool_episodes must be >= 1 and "
                         f"behaviour_episodes >= {EXPERT_EVERY}, got {n_expert}, {n_pool} and {n_behaviour}.")

    cache: dict[tuple[str, int], dict] = {}  # (policy, episode index) -> the episode, shared by the behaviour sets

    def behaviour_episode(kind: str, i: int) -> dict:
        if (kind, i) not in cache:
            policy = expert if kind == "expert" else uniform
            cache[kind, i] = collect_gym_episodes(task.env_id, policy, 1, seed=seed + 10_000 + i)[0]
        return cache[kind, i]

    expert_data = collect_gym_episodes(task.env_id, expert, n_expert, seed=seed)
    # one episode at a time: every fifth the expert's, the rest uniform random
    behaviour_kinds = ["expert" if i % EXPERT_EVERY == EXPERT_EVERY - 1 else "uniform" for i in range(n_behaviour)]
    behaviour = [behaviour_episode(kind, i) for i, kind in enumerate(behaviour_kinds)]
    random_ref = collect_gym_episodes(task.env_id, uniform, reference_episodes, seed=seed + 20_000)
    expert_ref = collect_gym_episodes(task.env_id, expert, reference_episodes, seed=seed + 30_000)
    ref_min, ref_max = float(_returns(random_ref).mean()), float(_returns(expert_ref).mean())

    noise = "Gaussian action noise, std 5% of the action range"
    common = dict(data_path=data_path, env=task.env_id, eval_env=task.env_id, ref_min_score=ref_min,
                  ref_max_score=ref_max, num_episodes_average_score=reference_episodes)
    write_minari_dataset(ids["expert"], expert_data, algorithm_name=f"{task.expert_description}; {noise}",
                         description=f"torchrl_wbrm benchmark: {task.env_id} expert, {n_expert} episodes",
                         metadata=_expert_ids(range(n_expert)), **common)
    write_minari_dataset(
        ids["behaviour"], behaviour,
        algorithm_name=f"uniform random actions; every {EXPERT_EVERY}th episode the expert ({noise})",
        description=f"torchrl_wbrm benchmark: {task.env_id} behaviour, {n_behaviour} episodes",
        metadata=_expert_ids(i for i, kind in enumerate(behaviour_kinds) if kind == "expert"), **common)

    def make_up(dataset_id, episodes, expert_eps, expert_steps):
        returns = _returns(episodes)
        return {"id": dataset_id, "episodes": len(episodes), "transitions": _steps(episodes),
                "expert_episodes": expert_eps, "expert_transitions": expert_steps,
                "return_mean": float(returns.mean()), "return_std": float(returns.std())}

    n_expert_behaviour = behaviour_kinds.count("expert")
    datasets = [
        make_up(ids["expert"], expert_data, n_expert, _steps(expert_data)),
        make_up(ids["behaviour"], behaviour, n_expert_behaviour,
                _steps([ep for ep, kind in zip(behaviour, behaviour_kinds) if kind == "expert"])),
    ]
    if few_demonstrations:
        pool = collect_gym_episodes(task.env_id, expert, n_pool, seed=seed + 40_000)
        write_minari_dataset(
            extra_ids["expert_pool"], pool, algorithm_name=f"{task.expert_description}; {noise}",
            description=f"torchrl_wbrm benchmark: {task.env_id} expert pool, {n_pool} episodes (draw a few with "
                        f"env.minari.expert_episodes)", metadata=_expert_ids(range(n_pool)), **common)
        datasets.append(make_up(extra_ids["expert_pool"], pool, n_pool, _steps(pool)))
        for dataset_name, share in EXPERT_SHARES.items():
            chosen = set(expert_episode_indices(n_behaviour, share))
            episodes = [behaviour_episode("expert" if i in chosen else "uniform", i) for i in range(n_behaviour)]
            dataset_id = extra_ids[dataset_name[:-3].replace("-", "_")]
            write_minari_dataset(
                dataset_id, episodes,
                algorithm_name=f"uniform random actions; {len(chosen)} of {n_behaviour} episodes the expert "
                               f"({noise}), evenly spread",
                description=f"torchrl_wbrm benchmark: {task.env_id} behaviour, {n_behaviour} episodes, "
                            f"{100 * share:.0f}% of them the expert's", metadata=_expert_ids(chosen), **common)
            datasets.append(make_up(dataset_id, episodes, len(chosen),
                                    _steps([episodes[i] for i in sorted(chosen)])))
        counter = [0]
        medium = [collect_gym_episodes(task.env_id, _medium(expert, uniform, counter), 1, seed=seed + 10_000 + i)[0]
                  for i in range(n_behaviour)]
        write_minari_dataset(
            extra_ids["medium"], medium,
            algorithm_name=f"every step the expert ({noise}) with probability {MEDIUM_EXPERT_PROBABILITY}, else "
                           f"uniform random actions",
            description=f"torchrl_wbrm benchmark: {task.env_id} medium, {n_behaviour} episodes",
            metadata=_expert_ids([]), **common)  # no episode is wholly the expert's
        datasets.append(make_up(extra_ids["medium"], medium, None, counter[0]))

    returns = {"random": _returns(random_ref), "behaviour": _returns(behaviour), "expert": _returns(expert_data)}
    return {
        "task": task.name, "env_id": task.env_id, **ids, **extra_ids,
        **{f"{kind}_path": str(root / dataset_id) for kind, dataset_id in {**ids, **extra_ids}.items()},
        "ref_min_score": ref_min, "ref_max_score": ref_max,
        **{f"{k}_return_mean": float(v.mean()) for k, v in returns.items()},
        **{f"{k}_return_std": float(v.std()) for k, v in returns.items()},
        "expert_transitions": _steps(expert_data),
        "behaviour_transitions": _steps(behaviour),
        "expert_episodes": n_expert, "behaviour_episodes": n_behaviour,
        "behaviour_normalised": float(normalised_score(returns["behaviour"].mean(), ref_min, ref_max)),
        "datasets": datasets,
    }


def check_benchmark_ids(names, data_path: str | os.PathLike, *, namespace: str = NAMESPACE,
                        few_demonstrations: bool = True, overwrite: bool = False) -> list:
    """The folders of every dataset the tasks ``names`` write under ``data_path``, each id checked first
    (:func:`~torchrl_wbrm.data.minari_data.check_new_minari_ids`): a valid Minari id, a folder inside the data path,
    and (unless ``overwrite``) new. Nothing is created or removed; a refusal is one line naming the id and
    ``--namespace``."""
    from torchrl_wbrm.data.minari_data import check_new_minari_ids

    dataset_ids = []
    for name in names:
        dataset_ids += list(benchmark_ids(name, namespace).values())
        if few_demonstrations:
            dataset_ids += list(few_demonstration_ids(name, namespace).values())
    folders = check_new_minari_ids(dataset_ids, data_path, setting="--namespace (or --data-path)", overwrite=True)
    if not overwrite:
        for dataset_id, path in zip(dataset_ids, folders):
            if path.exists():
                raise FileExistsError(f"The Minari dataset {dataset_id!r} already exists at {path}: pass "
                                      f"--overwrite to replace it, or another --data-path / --namespace.")
    return folders


def make_benchmark(data_path: str | os.PathLike, *, tasks=None, seed: int = 0, **kwargs) -> list[dict]:
    """:func:`make_benchmark_task` for each of ``tasks`` (default: every task of :data:`BENCHMARK_TASKS`)."""
    names = list(BENCHMARK_TASKS) if tasks is None else list(tasks)
    for name in names:
        if name not in BENCHMARK_TASKS:
            raise ValueError(f"Unknown benchmark task {name!r}: choose from {list(BENCHMARK_TASKS)}.")
        _check_simulator(BENCHMARK_TASKS[name])  # every missing simulator before any collecting
    check_benchmark_ids(names, data_path, namespace=kwargs.get("namespace", NAMESPACE),
                        few_demonstrations=kwargs.get("few_demonstrations", True),
                        overwrite=kwargs.get("overwrite", False))  # every id before anything is touched
    return [make_benchmark_task(name, data_path, seed=seed, **kwargs) for name in names]


def benchmark_table(rows: list[dict]) -> str:
    """The benchmark's datasets as Markdown: a table of the returns of random actions, the behaviour data and the
    expert (mean ± std over episodes), the behaviour's normalised score and the sizes; then, for rows that record
    it (``"datasets"``), each dataset's make-up: episodes, transitions, how many of them the expert's (for
    ``medium-v0``, the steps that took the expert's action) and the mean return ± std over its episodes."""
    lines = ["| task | env | random actions | behaviour data | expert data | behaviour, normalised | "
             "transitions (expert / behaviour) |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['task']} | {r['env_id']} | {r['random_return_mean']:.1f} ± {r['random_return_std']:.1f} | "
            f"{r['behaviour_return_mean']:.1f} ± {r['behaviour_return_std']:.1f} | "
            f"{r['expert_return_mean']:.1f} ± {r['expert_return_std']:.1f} | {r['behaviour_normalised']:.1f} | "
            f"{r['expert_transitions']:,} / {r['behaviour_transitions']:,} |")
    made_up = [r for r in rows if r.get("datasets")]
    if made_up:
        lines += ["", "| dataset | episodes | expert episodes | transitions | expert transitions | return |",
                  "|---|---|---|---|---|---|"]
        for r in made_up:
            for d in r["datasets"]:
                episodes = "—" if d["expert_episodes"] is None else f"{d['expert_episodes']:,}"
                share = d["expert_transitions"] / d["transitions"] if d["transitions"] else 0.0
                lines.append(f"| {d['id']} | {d['episodes']:,} | {episodes} | {d['transitions']:,} | "
                             f"{d['expert_transitions']:,} ({100 * share:.0f}%) | "
                             f"{d['return_mean']:.1f} ± {d['return_std']:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Write the torchrl_wbrm benchmark's Minari datasets.")
    parser.add_argument("--data-path", default="datasets/benchmark", help="Minari data path to write under")
    parser.add_argument("--tasks", nargs="+", default=None, choices=[*BENCHMARK_TASKS, *LOCOMOTION_DATASETS],
                        help=f"default: {' '.join(BENCHMARK_TASKS)}; the MuJoCo locomotion tasks "
                             f"({' '.join(LOCOMOTION_DATASETS)}) are written only when named")
    parser.add_argument("--expert-shares", nargs="+", type=int, default=list(DEFAULT_EXPERT_SHARES), metavar="PP",
                        help="locomotion: the random-expert<PP>-v0 sets, PP%% of the transitions the expert's")
    parser.add_argument("--transitions", type=int, default=DEFAULT_TRANSITIONS,
                        help="locomotion: the transitions of each random-expert<PP>-v0 and of medium-v0")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--reference-episodes", type=int, default=100)
    parser.add_argument("--namespace", default=NAMESPACE)
    parser.add_argument("--overwrite", action="store_true", help="replace datasets that already exist")
    parser.add_argument("--no-few-demonstrations", dest="few_demonstrations", action="store_false",
                        help="write only expert-v0 and behaviour-v0 (not the expert pool, the behaviour-expert<pp>-v0 "
                             "sets and medium-v0)")
    args = parser.parse_args(argv)
    small = [t for t in (args.tasks or BENCHMARK_TASKS) if t in BENCHMARK_TASKS]
    locomotion = [t for t in (args.tasks or ()) if t in LOCOMOTION_DATASETS]
    try:
        # every id of every task checked before anything is collected, removed or written
        check_locomotion_ids(locomotion, args.data_path, namespace=args.namespace, expert_shares=args.expert_shares,
                             overwrite=args.overwrite)
        rows = make_benchmark(args.data_path, tasks=small, seed=args.seed, overwrite=args.overwrite,
                              reference_episodes=args.reference_episodes, namespace=args.namespace,
                              few_demonstrations=args.few_demonstrations) if small else []
        locomotion_rows = [make_locomotion_task(name, args.data_path, seed=args.seed, namespace=args.namespace,
                                                transitions=args.transitions, expert_shares=args.expert_shares,
                                                overwrite=args.overwrite) for name in locomotion]
    except (ValueError, FileExistsError, ModuleNotFoundError) as err:  # refused before anything was written
        print(f"benchmark: refused: {' '.join(str(err).split())}", file=sys.stderr)
        sys.exit(2)
    except OSError as err:  # a full or read-only disk while writing: one line naming the file
        print(f"benchmark: stopped: {' '.join(str(err).split())}; a dataset being written under {args.data_path} may "
              f"be incomplete: run the command again with --overwrite once the disk is writable.", file=sys.stderr)
        sys.exit(1)
    except KeyboardInterrupt:
        print(f"benchmark: interrupted; a dataset being written under {args.data_path} may be incomplete: run the "
              f"command again with --overwrite to write it anew.", file=sys.stderr)
        sys.exit(130)
    if rows:
        print(benchmark_table(rows))
    if locomotion_rows:
        print(locomotion_table(locomotion_rows))
    for r in locomotion_rows:
        print(f"{r['task']}, few demonstrations: env.minari.data_path={args.data_path} "
              f"env.minari.expert={r['expert_pool']} env.minari.expert_episodes=5 "
              f"env.minari.behaviour={r['random_expert05'] if 'random_expert05' in r else r['medium']}")
    for r in rows:
        print(f"{r['task']}: env.minari.data_path={args.data_path} env.minari.expert={r['expert']} "
              f"env.minari.behaviour={r['behaviour']}")
        if args.few_demonstrations:
            print(f"{r['task']}, few demonstrations: env.minari.data_path={args.data_path} "
                  f"env.minari.expert={r['expert_pool']} env.minari.expert_episodes=3 "
                  f"env.minari.behaviour={r['behaviour_expert10']}")


if __name__ == "__main__":
    main()
