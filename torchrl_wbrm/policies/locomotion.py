"""Experts for gymnasium's MuJoCo locomotion tasks (``Hopper-v5``, ``HalfCheetah-v5``, ``Walker2d-v5``), trained
here with TorchRL's own online pieces, and their committed weights.

Unlike the hand-made controllers of :mod:`torchrl_wbrm.policies.gym_experts`, a locomotion expert is a trained
network. One command trains it with soft actor-critic: a torchrl :class:`~torchrl.collectors.Collector` over a
:class:`~torchrl.envs.GymEnv`, a :class:`~torchrl.data.ReplayBuffer` on a :class:`~torchrl.data.LazyTensorStorage`,
:class:`~torchrl.objectives.SACLoss` and :class:`~torchrl.objectives.SoftUpdate`, seeded; every
``--save-every`` frames it writes the deterministic actor (``tanh`` of the Gaussian's mean) with its measured
return, so that an earlier checkpoint can serve as a *medium* policy::

    python -m torchrl_wbrm.policies.locomotion --task hopper --seed 0 --frames 300000 --out experts_run

A run outlives its process: at each checkpoint the whole training state (networks, target networks, temperature,
optimiser, random generators, replay buffer, log) replaces ``<out>/state.pt`` in one atomic write, and rerunning
the same command continues from it, even after the process was killed. Each segment of ``--save-every`` frames
collects from an environment reset with a seed drawn from the run's seed and the segment's index, so a resumed run
is bit-identical to an uninterrupted one. A state written with other settings is refused, naming the setting.

The weights used by the datasets (:mod:`torchrl_wbrm.data.benchmark`) are committed in
``torchrl_wbrm/policies/experts/<task>-<level>.pt``, each with a ``.json`` record (seed, budget, measured return
and the bar a test holds it to). Loading never runs code: the file is read with ``torch.load(weights_only=True)``
and must hold exactly the tensors of the actor's architecture.
"""
from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from torchrl_wbrm._console import route_mujoco_warnings
from torchrl_wbrm._files import atomic_write

__all__ = [
    "EXPERTS_DIR",
    "LOCOMOTION_TASKS",
    "LocomotionActor",
    "commit_policies",
    "evaluate_policy",
    "load_locomotion_policy",
    "locomotion_record",
    "train_locomotion_expert",
]

#: the folder of the committed weights and their records
EXPERTS_DIR = Path(__file__).resolve().parent / "experts"

#: the tasks' short names and their gymnasium ids
LOCOMOTION_TASKS = {"hopper": "Hopper-v5", "halfcheetah": "HalfCheetah-v5", "walker2d": "Walker2d-v5"}

_HIDDEN = 256


class LocomotionActor(nn.Module):
    """The expert's deterministic actor: ``tanh(MLP(obs))`` in ``[−1, 1]`` (the three tasks' action box), the
    mean of the SAC actor's squashed Gaussian. ``forward`` takes ``[..., obs_dim]`` float32 observations."""

    def __init__(self, obs_dim: int, action_dim: int, hidden: int = _HIDDEN):
        super().__init__()
        self.obs_dim, self.action_dim, self.hidden = int(obs_dim), int(action_dim), int(hidden)
        self.net = nn.Sequential(nn.Linear(obs_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, 2 * action_dim))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.net(observation)[..., : self.action_dim])

    @torch.no_grad()
    def act(self, observation: np.ndarray) -> np.ndarray:
        """One action (or a batch) for NumPy observations, as float32 NumPy."""
        obs = torch.as_tensor(np.asarray(observation, dtype=np.float32))
        return self(obs).numpy()


def _task_id(task: str) -> str:
    if task not in LOCOMOTION_TASKS:
        raise ValueError(f"locomotion task {task!r} is not one of {sorted(LOCOMOTION_TASKS)}.")
    return LOCOMOTION_TASKS[task]


def locomotion_record(task: str, level: str = "expert", directory: str | Path | None = None) -> dict:
    """The ``.json`` record committed beside a policy's weights: its seed, training budget and measured return."""
    _task_id(task)
    path = Path(directory or EXPERTS_DIR) / f"{task}-{level}.json"
    if not path.is_file():
        raise FileNotFoundError(f"no {level} policy record for {task!r}: {path} does not exist.")
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a JSON record ({exc}).") from None
    if not isinstance(record, dict):
        raise ValueError(f"{path}: the record must be a JSON object, got {type(record).__name__}.")
    return record


def load_locomotion_policy(task: str, level: str = "expert", path: str | Path | None = None) -> LocomotionActor:
    """The committed ``level`` policy (``"expert"`` or ``"medium"``) of ``task``, or the weights at ``path``.

    The file is read with ``weights_only=True`` and must hold exactly the actor's tensors with their shapes; any
    other content is refused in one line naming the file."""
    import gymnasium as gym

    env_id = _task_id(task)
    path = Path(path) if path is not None else EXPERTS_DIR / f"{task}-{level}.pt"
    if not path.is_file():
        raise FileNotFoundError(f"no {level} policy for {task!r}: {path} does not exist.")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - unpickling errors come in many types; all mean "not our weights"
        raise ValueError(f"{path}: not a policy's weights ({type(exc).__name__}: {str(exc).splitlines()[0]}).") \
            from None
    route_mujoco_warnings()
    env = gym.make(env_id)
    obs_dim, action_dim = int(np.prod(env.observation_space.shape)), int(np.prod(env.action_space.shape))
    env.close()
    actor = LocomotionActor(obs_dim, action_dim)
    expected = {k: tuple(v.shape) for k, v in actor.state_dict().items()}
    if not isinstance(state, dict) or {k: tuple(getattr(v, "shape", ())) for k, v in state.items()} != expected:
        raise ValueError(f"{path}: does not hold the {env_id} actor's tensors {expected}.")
    if not all(torch.is_tensor(v) and v.dtype == torch.float32 and bool(torch.isfinite(v).all())
               for v in state.values()):
        raise ValueError(f"{path}: the actor's tensors must be finite float32.")
    actor.load_state_dict(state)
    actor.eval()
    return actor


def evaluate_policy(actor: LocomotionActor, env_id: str, episodes: int, seed: int) -> np.ndarray:
    """The undiscounted returns of ``actor`` over ``episodes`` episodes of ``env_id``, all run at once in a
    gymnasium vector env (one reset seed per episode, ``seed + i``)."""
    import gymnasium as gym

    route_mujoco_warnings()
    envs = gym.vector.SyncVectorEnv([lambda: gym.make(env_id) for _ in range(episodes)],
                                    autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
    obs, _ = envs.reset(seed=[seed + i for i in range(episodes)])
    returns = np.zeros(episodes)
    alive = np.ones(episodes, dtype=bool)
    while alive.any():
        obs, reward, term, trunc, _ = envs.step(actor.act(obs))
        returns += reward * alive
        alive &= ~(term | trunc)
    envs.close()
    return returns


@dataclass
class _TrainConfig:
    task: str
    seed: int
    frames: int
    out: Path
    init_random_frames: int = 10_000
    frames_per_batch: int = 1_000
    batch_size: int = 256
    lr: float = 3e-4
    gamma: float = 0.99
    tau: float = 0.005
    save_every: int = 25_000
    eval_episodes: int = 10
    hidden: int = _HIDDEN


#: the settings a run's state is written with: a resume must give the same ones
_RUN_SETTINGS = ("task", "seed", "frames", "save_every", "init_random_frames", "frames_per_batch", "batch_size", "lr",
                 "gamma", "tau", "eval_episodes", "hidden")
#: the command-line names of the settings that have one
_FLAGS = {"task": "--task", "seed": "--seed", "frames": "--frames", "save_every": "--save-every"}
#: what the replay buffer keeps of a collected transition: what ``SACLoss`` reads
_BUFFER_KEYS = ("observation", "action", ("next", "observation"), ("next", "reward"), ("next", "done"),
                ("next", "terminated"))
_STATE = "state.pt"
_STATE_FORMAT = 1


def _segment_seed(seed: int, segment: int) -> int:
    """The reset seed of the environment for segment ``segment`` of a run seeded ``seed``."""
    return int(np.random.SeedSequence([seed, segment]).generate_state(1)[0])


def _settings(cfg: _TrainConfig) -> dict:
    return {key: getattr(cfg, key) for key in _RUN_SETTINGS}


def _read_state(path: Path, cfg: _TrainConfig) -> dict:
    """The run state at ``path``, read with ``weights_only=True``; refused in one line naming the file, or the
    setting it was written with that ``cfg`` does not give."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - unpickling errors come in many types; all mean "not our state"
        raise ValueError(f"{path}: not a run state ({type(exc).__name__}: {str(exc).splitlines()[0]}).") from None
    if not isinstance(state, dict) or state.get("format") != _STATE_FORMAT or not isinstance(state.get("settings"),
                                                                                               dict):
        raise ValueError(f"{path}: not a run state of this trainer (format {_STATE_FORMAT}).")
    for key, given in _settings(cfg).items():
        saved = state["settings"].get(key)
        if saved != given:
            name = _FLAGS.get(key, key)
            raise ValueError(f"{path}: the run was started with {name} {saved!r}, not {given!r}; rerun it with the "
                             f"same settings, or give another --out.")
    frames = state.get("frames")
    if not isinstance(frames, int) or not 0 < frames <= cfg.frames or (frames % cfg.save_every
                                                                        and frames != cfg.frames):
        raise ValueError(f"{path}: frames {frames!r} is not a segment end of a {cfg.frames}-frame run.")
    return state


def _numpy_rng_state() -> dict:
    name, keys, pos, has_gauss, cached = np.random.get_state()
    return {"name": name, "keys": torch.from_numpy(keys.astype(np.int64)), "pos": int(pos),
            "has_gauss": int(has_gauss), "cached_gaussian": float(cached)}


def _set_numpy_rng_state(state: dict) -> None:
    np.random.set_state((state["name"], state["keys"].numpy().astype(np.uint32), state["pos"], state["has_gauss"],
                         state["cached_gaussian"]))


def train_locomotion_expert(cfg: _TrainConfig, log=print) -> dict:
    """Train a SAC expert with torchrl's collector, buffer, loss and updater; returns the last evaluation.

    The run is cut into segments of ``cfg.save_every`` frames, each with its own collector over an environment
    reset with a seed drawn from ``(cfg.seed, segment)``. At each segment's end the deterministic actor
    (``<task>-<frames>.pt``) and the log (``<task>-log.json``) are written, then the whole state (networks, target
    networks, temperature, optimiser, random generators, replay buffer, log) replaces ``cfg.out/state.pt`` in one
    atomic write. Called again with the same settings, it continues from that state, and the run is bit-identical
    to one never interrupted; other settings are refused in one line naming the setting."""
    from tensordict import TensorDict
    from tensordict.nn import NormalParamExtractor, TensorDictModule
    from torchrl.collectors import Collector
    from torchrl.data import LazyTensorStorage, ReplayBuffer
    from torchrl.envs import Compose, DoubleToFloat, GymEnv, TransformedEnv
    from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator
    from torchrl.objectives import SACLoss, SoftUpdate

    env_id = _task_id(cfg.task)
    for key in ("frames", "save_every", "init_random_frames"):
        value = getattr(cfg, key)
        if value < 0 or value % cfg.frames_per_batch or (value == 0 and key != "init_random_frames"):
            raise ValueError(f"{_FLAGS.get(key, key)} {value} must be a positive multiple of frames_per_batch "
                             f"({cfg.frames_per_batch}).")
    state_path = cfg.out / _STATE
    state = _read_state(state_path, cfg) if state_path.is_file() else None
    if state is None and (any(cfg.out.glob(f"{cfg.task}-*.pt")) or (cfg.out / f"{cfg.task}-log.json").exists()):
        raise FileExistsError(f"{cfg.out} holds {cfg.task} checkpoints but no {_STATE} to continue from; give "
                              f"another --out.")

    route_mujoco_warnings()

    def make_env():
        return TransformedEnv(GymEnv(env_id), Compose(DoubleToFloat()))

    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    env = make_env()
    obs_dim = env.observation_spec["observation"].shape[-1]
    action_dim = env.action_spec.shape[-1]
    action_spec = env.action_spec
    env.close()

    deterministic = LocomotionActor(obs_dim, action_dim, cfg.hidden)
    actor_module = TensorDictModule(nn.Sequential(deterministic.net, NormalParamExtractor()),
                                    in_keys=["observation"], out_keys=["loc", "scale"])
    actor = ProbabilisticActor(actor_module, in_keys=["loc", "scale"], spec=action_spec,
                               distribution_class=TanhNormal, return_log_prob=False,
                               distribution_kwargs={"low": action_spec.space.low, "high": action_spec.space.high})
    qvalue = ValueOperator(MLP(in_features=obs_dim + action_dim, out_features=1, num_cells=[cfg.hidden, cfg.hidden],
                               activation_class=nn.ReLU), in_keys=["observation", "action"])
    loss = SACLoss(actor, qvalue, num_qvalue_nets=2, loss_function="l2", action_spec=action_spec)
    loss.make_value_estimator(gamma=cfg.gamma)
    updater = SoftUpdate(loss, tau=cfg.tau)
    optim = torch.optim.Adam(loss.parameters(), lr=cfg.lr)
    buffer = ReplayBuffer(storage=LazyTensorStorage(cfg.frames), batch_size=cfg.batch_size)

    frames, entries, elapsed = 0, [], 0.0
    if state is not None:
        try:
            loss.load_state_dict(state["loss"])
            optim.load_state_dict(state["optim"])
            rows = TensorDict(state["buffer"], batch_size=[state["frames"]]).unflatten_keys(".")
            if set(rows.keys(True, True)) != set(_BUFFER_KEYS):
                raise ValueError(f"the buffer holds {list(rows.keys(True, True))}, not {list(_BUFFER_KEYS)}")
            buffer.extend(rows)
            torch.set_rng_state(state["torch_rng"])
            _set_numpy_rng_state(state["numpy_rng"])
            frames, entries, elapsed = state["frames"], list(state["log"]), float(state["elapsed"])
        except Exception as exc:  # noqa: BLE001 - a state that does not fit this run, whatever the reason
            raise ValueError(f"{state_path}: does not fit this run ({type(exc).__name__}: "
                             f"{str(exc).splitlines()[0]}).") from None
        log(json.dumps({"resumed": str(state_path), "frames": frames}))
    cfg.out.mkdir(parents=True, exist_ok=True)
    for pattern in (f".{_STATE}.*.tmp", f".{cfg.task}-*.tmp"):  # this trainer's writes cut short by a kill
        for stale in cfg.out.glob(pattern):
            stale.unlink()
    start = time.time()
    while frames < cfg.frames:
        segment = frames // cfg.save_every
        env = make_env()
        env.set_seed(_segment_seed(cfg.seed, segment))
        collector = Collector(env, actor, frames_per_batch=cfg.frames_per_batch,
                              total_frames=min(cfg.save_every, cfg.frames - frames),
                              init_random_frames=max(0, cfg.init_random_frames - frames) or None,
                              auto_register_policy_transforms=False)
        for batch in collector:
            buffer.extend(batch.reshape(-1).select(*_BUFFER_KEYS))
            frames += batch.numel()
            if frames >= cfg.init_random_frames:
                for _ in range(batch.numel()):
                    losses = loss(buffer.sample())
                    total = losses["loss_actor"] + losses["loss_qvalue"] + losses["loss_alpha"]
                    optim.zero_grad()
                    total.backward()
                    optim.step()
                    updater.step()
        collector.shutdown()
        returns = evaluate_policy(deterministic, env_id, cfg.eval_episodes, seed=10_000 + frames)
        entry = {"frames": frames, "return_mean": float(returns.mean()), "return_std": float(returns.std()),
                 "seconds": round(elapsed + time.time() - start, 1)}
        entries.append(entry)
        atomic_write(cfg.out / f"{cfg.task}-{frames:08d}.pt", lambda f: torch.save(deterministic.state_dict(), f))
        atomic_write(cfg.out / f"{cfg.task}-log.json", lambda f: f.write(json.dumps(entries, indent=1).encode()))
        rows = buffer[: len(buffer)].flatten_keys(".")
        snapshot = {"format": _STATE_FORMAT, "settings": _settings(cfg), "frames": frames, "log": entries,
                    "elapsed": elapsed + time.time() - start, "loss": loss.state_dict(), "optim": optim.state_dict(),
                    "torch_rng": torch.get_rng_state(), "numpy_rng": _numpy_rng_state(),
                    "buffer": {key: rows.get(key).clone() for key in rows.keys()}}  # not the unfilled rows
        log(json.dumps(entry))
        written = time.time()
        atomic_write(state_path, lambda f, snapshot=snapshot: torch.save(snapshot, f))
        log(json.dumps({"state": str(state_path), "frames": frames, "bytes": state_path.stat().st_size,
                        "write_seconds": round(time.time() - written, 2)}))
    return entries[-1]


def _ci95(values: np.ndarray) -> float:
    return float(1.96 * values.std(ddof=1) / math.sqrt(len(values))) if len(values) > 1 else float("nan")


def commit_policies(task: str, run_dir: Path, *, seed: int, frames: int, episodes: int = 100,
                    directory: Path = EXPERTS_DIR, log=print) -> dict:
    """Measure a training run's last checkpoint (the expert) and the checkpoint whose logged return is closest to a
    third of it (the medium policy) over ``episodes`` episodes each, and write them with their records into
    ``directory`` as ``<task>-expert`` and ``<task>-medium`` (``.pt`` and ``.json``). A record states the training
    seed and budget, the return's mean ± 95% CI over the episodes and ``test_bar``, 90% of their 10th percentile:
    the bar a test holds the policy's mean return over a few episodes to."""
    env_id = _task_id(task)
    checkpoints = sorted(run_dir.glob(f"{task}-*.pt"))
    if not checkpoints:
        raise FileNotFoundError(f"{run_dir} holds no {task}-<frames>.pt checkpoint.")
    logged = {int(e["frames"]): e for e in json.loads((run_dir / f"{task}-log.json").read_text(encoding="utf-8"))}
    by_frames = {int(p.stem.rsplit("-", 1)[1]): p for p in checkpoints}
    last = max(by_frames)
    out = {}
    expert_returns = None
    for level in ("expert", "medium"):
        if level == "expert":
            chosen = last
        else:
            target = float(expert_returns.mean()) / 3
            chosen = min((f for f in by_frames if f < last and f in logged),
                         key=lambda f: abs(logged[f]["return_mean"] - target))
        actor = load_locomotion_policy(task, path=by_frames[chosen])
        returns = evaluate_policy(actor, env_id, episodes, seed=1_000_000)
        if level == "expert":
            expert_returns = returns
        record = {"env_id": env_id, "level": level, "algorithm": "SAC (torchrl SACLoss), deterministic actor",
                  "seed": seed, "frames": chosen, "budget_frames": frames, "episodes": episodes,
                  "evaluation_seeds": f"1000000..{1_000_000 + episodes - 1}",
                  "return_mean": round(float(returns.mean()), 1), "return_ci95": round(_ci95(returns), 1),
                  "return_min": round(float(returns.min()), 1),
                  "test_bar": round(0.9 * float(np.percentile(returns, 10)), 1)}
        torch.save(actor.state_dict(), directory / f"{task}-{level}.pt")
        (directory / f"{task}-{level}.json").write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
        log(json.dumps(record))
        out[level] = record
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Train a SAC expert for a MuJoCo locomotion task with torchrl, "
                                                 "or measure a saved policy's return.")
    parser.add_argument("--task", required=True, choices=sorted(LOCOMOTION_TASKS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frames", type=int, default=300_000, help="environment steps (one update per step)")
    parser.add_argument("--out", type=Path, default=Path("experts_run"),
                        help="folder for the checkpoints, the training log and the run's state (state.pt): rerun "
                             "the same command to continue a run from its last checkpoint")
    parser.add_argument("--save-every", type=int, default=25_000,
                        help="frames per segment: a checkpoint, an evaluation and the run's state after each")
    parser.add_argument("--measure", type=Path, default=None,
                        help="instead of training, measure the return of these weights over --episodes")
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1: one core)")
    parser.add_argument("--commit", action="store_true",
                        help="instead of training, measure the run in --out (its last checkpoint and the one nearest a "
                             "third of its return) and write them as the committed expert and medium policies")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.commit:
        EXPERTS_DIR.mkdir(exist_ok=True)
        commit_policies(args.task, args.out, seed=args.seed, frames=args.frames, episodes=args.episodes)
        return
    if args.measure is not None:
        actor = load_locomotion_policy(args.task, path=args.measure)
        returns = evaluate_policy(actor, LOCOMOTION_TASKS[args.task], args.episodes, seed=1_000_000)
        print(json.dumps({"task": args.task, "weights": str(args.measure), "episodes": args.episodes,
                          "return_mean": round(float(returns.mean()), 1), "return_ci95": round(_ci95(returns), 1),
                          "return_min": round(float(returns.min()), 1)}))
        return
    try:
        train_locomotion_expert(_TrainConfig(task=args.task, seed=args.seed, frames=args.frames, out=args.out,
                                             save_every=args.save_every))
    except (ValueError, FileExistsError) as exc:
        raise SystemExit(f"error: {exc}") from None


if __name__ == "__main__":
    main()
