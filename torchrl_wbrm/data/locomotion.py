"""D4RL-style datasets of gymnasium's MuJoCo locomotion tasks, made here in Minari format from the experts trained
by :mod:`torchrl_wbrm.policies.locomotion`.

For each task (``hopper``, ``halfcheetah``, ``walker2d``; :data:`LOCOMOTION_DATASETS`) and a size of ``T``
transitions (default :data:`DEFAULT_TRANSITIONS`):

* ``<ns>/<task>/expert-pool-v0``: whole episodes of the noisy expert (the committed actor plus Gaussian noise of
  standard deviation 5% of the action range, clipped), reset seeds ``seed + 40_000 + i``; a run draws its few
  demonstrations from it by its own seed (``env.minari.expert_episodes``);
* ``<ns>/<task>/random-expert<PP>-v0`` for each ``PP`` of ``expert_shares`` (default 1, 5 and 10): uniform random
  actions, with ``PP``% of the **transitions** (Hong et al.'s definition, not of the episodes: a random Hopper
  episode lasts about 20 steps, the expert's 1,000) from whole noisy-expert episodes, spread evenly among the
  random ones. The expert episodes are the first ones of one sequence (reset seeds ``seed + 10_000 + i``) and the
  random episodes the first ones of another (``seed + 50_000 + j``), so a 1% set's episodes are in the 5% set too;
* ``<ns>/<task>/medium-v0``: the committed *medium* policy (an earlier checkpoint of the expert's training, at
  about a third of its return) with the same noise, ``T`` transitions of whole episodes.

Each dataset records D4RL's reference scores (:data:`D4RL_REFERENCE_SCORES`: the returns of random actions and
of D4RL's expert), so a run's ``final.normalised_score`` is D4RL's normalised score, and its ``metadata.json``
names its expert episodes (``expert_episode_ids``) as the small tasks' datasets do.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from torchrl_wbrm._console import route_mujoco_warnings
from torchrl_wbrm.data.minari_data import check_new_minari_ids, write_minari_dataset
from torchrl_wbrm.data.minari_examples import collect_gym_episodes

__all__ = [
    "D4RL_REFERENCE_SCORES",
    "DEFAULT_EXPERT_SHARES",
    "DEFAULT_TRANSITIONS",
    "LOCOMOTION_DATASETS",
    "LocomotionTask",
    "check_locomotion_ids",
    "locomotion_ids",
    "locomotion_table",
    "make_locomotion_task",
    "mixture_plan",
]

#: D4RL's reference returns (random, expert) for the v2 MuJoCo datasets, the field's normaliser
D4RL_REFERENCE_SCORES = {
    "hopper": (-20.272305, 3234.3),
    "halfcheetah": (-280.178953, 12135.0),
    "walker2d": (1.629008, 4592.3),
}

#: D4RL's dataset size
DEFAULT_TRANSITIONS = 1_000_000

#: the default ``random-expert<PP>-v0`` shares, in percent of the transitions
DEFAULT_EXPERT_SHARES = (1, 5, 10)

#: the expert-pool's episodes (a run draws 1 to 5 of them)
DEFAULT_POOL_EPISODES = 20

#: the noise of the noisy expert and medium policies: this fraction of the action range, as a Gaussian std
NOISE_FRACTION = 0.05


@dataclass(frozen=True)
class LocomotionTask:
    """One locomotion task: its short name and gymnasium id."""

    name: str
    env_id: str


LOCOMOTION_DATASETS: dict[str, LocomotionTask] = {
    t.name: t for t in (LocomotionTask("hopper", "Hopper-v5"), LocomotionTask("halfcheetah", "HalfCheetah-v5"),
                        LocomotionTask("walker2d", "Walker2d-v5"))
}


def _share_name(percent: int) -> str:
    return f"random-expert{percent:02d}-v0"


def locomotion_ids(name: str, namespace: str, expert_shares=DEFAULT_EXPERT_SHARES) -> dict[str, str]:
    """The dataset ids of task ``name``: ``expert_pool``, ``random_expert<PP>`` for each share, and ``medium``."""
    ids = {"expert_pool": f"{namespace}/{name}/expert-pool-v0"}
    for pp in expert_shares:
        ids[f"random_expert{pp:02d}"] = f"{namespace}/{name}/{_share_name(pp)}"
    ids["medium"] = f"{namespace}/{name}/medium-v0"
    return ids


def _check_shares(expert_shares) -> tuple[int, ...]:
    shares = tuple(expert_shares)
    for pp in shares:
        if isinstance(pp, bool) or not isinstance(pp, (int, np.integer)) or not 1 <= pp <= 99:
            raise ValueError(f"--expert-shares: each share must be an integer percentage in [1, 99], got {pp!r}.")
    if len(set(shares)) != len(shares):
        raise ValueError(f"--expert-shares: {list(shares)} names a share twice.")
    return tuple(int(pp) for pp in shares)


def mixture_plan(expert_lengths, random_lengths, transitions: int, percent: int) -> tuple[int, int]:
    """How many of the expert episodes and of the random episodes (each taken from the start of its sequence) make
    a set of at least ``transitions`` transitions of which ``percent``% are the expert's: the fewest expert
    episodes whose steps reach ``percent``% of ``transitions``, then the fewest random ones that fill the rest.

        >>> mixture_plan([1000] * 10, [20] * 1000, 10_000, 10)
        (1, 450)
    """
    expert_cum = np.cumsum(expert_lengths)
    need = percent / 100.0 * transitions
    k = int(np.searchsorted(expert_cum, need - 1e-9) + 1)
    if k > len(expert_lengths):
        raise ValueError(f"mixture_plan: {expert_cum[-1] if len(expert_cum) else 0} expert steps cannot give "
                         f"{percent}% of {transitions}.")
    rest = transitions - int(expert_cum[k - 1])
    random_cum = np.cumsum(random_lengths)
    m = 0 if rest <= 0 else int(np.searchsorted(random_cum, rest - 1e-9) + 1)
    if m > len(random_lengths):
        raise ValueError(f"mixture_plan: {random_cum[-1]} random steps cannot fill {rest}.")
    return k, m


def _interleave(n_expert: int, n_random: int) -> list[tuple[str, int]]:
    """The order of a mixture's episodes: the expert's spread evenly among the random ones."""
    total = n_expert + n_random
    expert_at = {(j + 1) * total // (n_expert + 1) for j in range(n_expert)} if n_expert else set()
    order, e, r = [], 0, 0
    for i in range(total):
        if i in expert_at and e < n_expert:
            order.append(("expert", e))
            e += 1
        elif r < n_random:
            order.append(("random", r))
            r += 1
        else:
            order.append(("expert", e))
            e += 1
    return order


def _collect_until(env_id: str, policy, steps: int, seed: int, chunk: int) -> list[dict]:
    """Whole episodes (reset seeds ``seed``, ``seed + 1``, ...) until their steps reach ``steps``."""
    episodes, total, i = [], 0, 0
    while total < steps:
        batch = collect_gym_episodes(env_id, policy, chunk, seed=seed + i)
        for ep in batch:
            if total >= steps:
                break
            episodes.append(ep)
            total += len(ep["rewards"])
        i += chunk
    return episodes


def _steps(episodes) -> int:
    return int(sum(len(ep["rewards"]) for ep in episodes))


def check_locomotion_ids(names, data_path, *, namespace: str = "benchmark", expert_shares=DEFAULT_EXPERT_SHARES,
                         overwrite: bool = False) -> list:
    """The folders of every dataset the tasks ``names`` write, each id checked first (a valid Minari id, a folder
    inside the data path, new unless ``overwrite``); nothing is created or removed."""
    shares = _check_shares(expert_shares)
    dataset_ids = []
    for name in names:
        if name not in LOCOMOTION_DATASETS:
            raise ValueError(f"Unknown locomotion task {name!r}: choose from {sorted(LOCOMOTION_DATASETS)}.")
        dataset_ids += list(locomotion_ids(name, namespace, shares).values())
    return check_new_minari_ids(dataset_ids, data_path, setting="--namespace (or --data-path)", overwrite=overwrite)


def locomotion_table(rows: list[dict]) -> str:
    """The locomotion datasets' make-up as Markdown: episodes, transitions, the expert's episodes and transitions
    (and their share), the mean return ± std over episodes, D4RL's normalised score of that mean and the seconds."""
    lines = ["| dataset | episodes | expert episodes | transitions | expert transitions | return | normalised | "
             "seconds |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for d in r["datasets"]:
            share = d["expert_transitions"] / d["transitions"]
            score = 100 * (d["return_mean"] - r["ref_min_score"]) / (r["ref_max_score"] - r["ref_min_score"])
            lines.append(f"| {d['id']} | {d['episodes']:,} | {d['expert_episodes']:,} | {d['transitions']:,} | "
                         f"{d['expert_transitions']:,} ({100 * share:.1f}%) | {d['return_mean']:.1f} ± "
                         f"{d['return_std']:.1f} | {score:.1f} | {d['seconds']:.0f} |")
    return "\n".join(lines)


def make_locomotion_task(name: str, data_path, *, seed: int = 0, namespace: str = "benchmark",
                         transitions: int = DEFAULT_TRANSITIONS, expert_shares=DEFAULT_EXPERT_SHARES,
                         pool_episodes: int = DEFAULT_POOL_EPISODES, overwrite: bool = False,
                         medium: bool = True, log=print) -> dict:
    """Write task ``name``'s datasets under ``data_path``; returns their ids and make-up (``"datasets"``: episodes,
    transitions, the expert's episodes and transitions, the mean return), the reference scores and the seconds
    the collection took. Every id is validated, and an existing one refused unless ``overwrite``, before anything
    is collected or removed. ``medium=False`` writes no ``medium-v0`` (and names none)."""
    import shutil

    from torchrl_wbrm.policies.locomotion import load_locomotion_policy

    if name not in LOCOMOTION_DATASETS:
        raise ValueError(f"Unknown locomotion task {name!r}: choose from {sorted(LOCOMOTION_DATASETS)}.")
    task = LOCOMOTION_DATASETS[name]
    shares = _check_shares(expert_shares)
    if int(transitions) < 1000:
        raise ValueError(f"--transitions must be at least 1000, got {transitions}.")
    ids = locomotion_ids(name, namespace, shares)
    if not medium:
        del ids["medium"]
    # every id checked (syntax, inside the data path, new unless overwrite) before anything is removed or written
    folders = check_new_minari_ids(ids.values(), data_path, setting="--namespace (or --data-path)",
                                   overwrite=overwrite)
    for folder in folders:
        if folder.exists():  # overwrite: the old dataset, inside the data path (checked above)
            shutil.rmtree(folder)

    import gymnasium as gym

    route_mujoco_warnings()
    env = gym.make(task.env_id)
    low, high = env.action_space.low.astype(np.float32), env.action_space.high.astype(np.float32)
    env.close()
    std = NOISE_FRACTION * (high - low)
    start = time.time()

    def noisy(actor):
        def policy(obs, rng):
            return np.clip(actor.act(obs) + rng.normal(0.0, 1.0, low.shape).astype(np.float32) * std, low, high)
        return policy

    def uniform(obs, rng):
        return rng.uniform(low, high).astype(np.float32)

    expert = noisy(load_locomotion_policy(name, "expert"))
    medium_policy = noisy(load_locomotion_policy(name, "medium")) if medium else None
    ref_min, ref_max = D4RL_REFERENCE_SCORES[name]
    common = dict(data_path=data_path, env=task.env_id, eval_env=task.env_id, ref_min_score=ref_min,
                  ref_max_score=ref_max)
    noise = f"Gaussian action noise, std {100 * NOISE_FRACTION:.0f}% of the action range"
    datasets = []

    def make_up(dataset_id, episodes, expert_ids, seconds):
        returns = np.array([float(np.sum(ep["rewards"])) for ep in episodes])
        expert_steps = _steps(episodes[i] for i in expert_ids)
        row = {"id": dataset_id, "episodes": len(episodes), "transitions": _steps(episodes),
               "expert_episodes": len(expert_ids), "expert_transitions": expert_steps,
               "return_mean": float(returns.mean()), "return_std": float(returns.std()),
               "seconds": round(seconds, 1)}
        datasets.append(row)
        log(f"{dataset_id}: {row['episodes']:,} episodes, {row['transitions']:,} transitions, "
            f"{row['expert_episodes']} expert episodes ({expert_steps:,} transitions), return "
            f"{row['return_mean']:.1f} ± {row['return_std']:.1f}, {seconds:.0f} s")

    t0 = time.time()
    pool = collect_gym_episodes(task.env_id, expert, pool_episodes, seed=seed + 40_000)
    write_minari_dataset(ids["expert_pool"], pool, algorithm_name=f"SAC expert trained here; {noise}",
                         description=f"torchrl_wbrm benchmark: {task.env_id} expert pool, {pool_episodes} episodes",
                         metadata={"expert_episode_ids": list(range(len(pool)))}, **common)
    make_up(ids["expert_pool"], pool, list(range(len(pool))), time.time() - t0)

    t0 = time.time()
    max_pp = max(shares)
    expert_eps = _collect_until(task.env_id, expert, int(np.ceil(max_pp / 100 * transitions)), seed + 10_000, 4)
    random_eps = _collect_until(task.env_id, uniform, int(transitions * (1 - min(shares) / 100)), seed + 50_000,
                                256)
    collect_seconds = time.time() - t0
    for pp in shares:
        t0 = time.time()
        k, m = mixture_plan([len(ep["rewards"]) for ep in expert_eps], [len(ep["rewards"]) for ep in random_eps],
                            transitions, pp)
        order = _interleave(k, m)
        episodes = [expert_eps[i] if kind == "expert" else random_eps[i] for kind, i in order]
        expert_ids = [j for j, (kind, _) in enumerate(order) if kind == "expert"]
        dataset_id = ids[f"random_expert{pp:02d}"]
        write_minari_dataset(
            dataset_id, episodes,
            algorithm_name=f"uniform random actions; {pp}% of the transitions from the SAC expert ({noise}), "
                           f"whole episodes spread evenly",
            description=f"torchrl_wbrm benchmark: {task.env_id} random-expert {pp}%, {_steps(episodes):,} "
                        f"transitions", metadata={"expert_episode_ids": expert_ids}, **common)
        make_up(dataset_id, episodes, expert_ids, time.time() - t0 + collect_seconds / len(shares))

    if medium:
        t0 = time.time()
        episodes = _collect_until(task.env_id, medium_policy, transitions, seed + 60_000, 4)
        write_minari_dataset(ids["medium"], episodes,
                             algorithm_name=f"an earlier checkpoint of the SAC expert; {noise}",
                             description=f"torchrl_wbrm benchmark: {task.env_id} medium, {_steps(episodes):,} "
                                         f"transitions", metadata={"expert_episode_ids": []}, **common)
        make_up(ids["medium"], episodes, [], time.time() - t0)
    return {"task": name, "env_id": task.env_id, **ids, "ref_min_score": ref_min, "ref_max_score": ref_max,
            "datasets": datasets, "seconds": round(time.time() - start, 1)}
