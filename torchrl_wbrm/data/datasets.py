"""Offline datasets: collection with torchrl's ``Collector``, the paper's split, replay buffers, save/load.

The paper (Section 3) needs three independent sets:

* ``D`` — behaviour transitions ``(x, a, r, x')`` for the Bellman residual (``transitions``);
* ``S^b`` — behaviour state-action samples for the density ratio (``behaviour_samples``);
* ``S^e`` — expert state-action samples for the density ratio (``expert_samples``).

``D`` and ``S^b`` come from one behaviour collection split by *episode* (so the two sets are disjoint and
independent, as the paper requires ``S`` independent of ``D``). Each set lives in a ``TensorDictReplayBuffer``
over a ``LazyTensorStorage`` (or a ``LazyMemmapStorage`` for data larger than memory); paired ratio batches
``TensorDict({"behaviour": ..., "expert": ...})`` are drawn through torchrl's ``ReplayBufferEnsemble``.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import Collector
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, ReplayBufferEnsemble, TensorDictReplayBuffer

__all__ = [
    "OfflineDatasets",
    "collect_transitions",
    "split_by_episode",
    "make_replay_buffer",
    "FORMAT_VERSION",
    "TRANSITION_KEYS",
    "PairedSampler",
    "episode_returns",
]

FORMAT_VERSION = 1
#: Keys every transition set must hold.
TRANSITION_KEYS = (
    "observation",
    "action",
    ("next", "observation"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
    ("next", "truncated"),
)
STATE_ACTION_KEYS = ("observation", "action")
PARTS = ("transitions", "behaviour_samples", "expert_samples")
#: torch's global generator (policy noise) is seeded with ``seed + POLICY_SEED_OFFSET``, the env with ``seed``.
POLICY_SEED_OFFSET = 7_919_981


def collect_transitions(
    env,
    policy: Callable | None,
    total_frames: int,
    *,
    frames_per_batch: int | None = None,
    seed: int | None = None,
    episode_offset: int = 0,
) -> TensorDict:
    """Run ``policy`` in ``env`` with a torchrl ``Collector`` and return ``total_frames`` flat transitions.

    For a batched env (batch ``[N]``) one collector batch is ``N * horizon`` frames (whole episodes); the result
    is flattened to ``[frames]``. Each transition gets an integer ``"episode"`` id (the collector's trajectory
    id, shifted by ``episode_offset``), used to split sets by episode.

    Args:
        env: a torchrl env (its batch size sets the number of parallel episodes).
        policy: a TensorDictModule, or ``None`` for uniform random actions.
        total_frames: number of transitions to return.
        frames_per_batch: collector batch (defaults to ``min(total_frames, env.batch_size.numel() * 1000)``,
            rounded to a multiple of the env's batch size).
        seed: seeds the env (``collector.set_seed(seed)``) and torch's global generator (the policies' noise)
            with a *different* seed: an env generator and torch's generator seeded alike draw the same
            numbers, which would correlate the action noise with the initial state and the transition noise.
            The global generator's state is restored afterwards.
        episode_offset: added to the episode ids.
    """
    if total_frames <= 0:
        raise ValueError(f"total_frames must be > 0, got {total_frames}.")
    n_envs = max(env.batch_size.numel(), 1)
    if frames_per_batch is None:
        frames_per_batch = min(total_frames, n_envs * 1000)
    frames_per_batch = max(n_envs, (frames_per_batch // n_envs) * n_envs)
    total = math.ceil(total_frames / frames_per_batch) * frames_per_batch
    batches = []
    # a seeded collection runs on a forked global generator: it neither depends on nor disturbs the caller's state
    with torch.random.fork_rng(enabled=seed is not None):
        if seed is not None:
            torch.manual_seed(seed + POLICY_SEED_OFFSET)
        collector = Collector(
            env, policy, frames_per_batch=frames_per_batch, total_frames=total, auto_register_policy_transforms=False
        )
        if seed is not None:
            collector.set_seed(seed)
        try:
            for batch in collector:
                batches.append(batch.reshape(-1).clone())  # the collector reuses its buffers
        finally:
            collector.shutdown(close_env=False)
    data = torch.cat(batches, 0)[:total_frames]
    episode = data.get(("collector", "traj_ids")).clone()
    data = data.exclude("collector")
    data.set("episode", episode + episode_offset)
    missing = [k for k in TRANSITION_KEYS if k not in data.keys(True)]
    if missing:
        raise KeyError(f"The collected data lacks {missing}: does the env declare them in its specs?")
    return data


def split_by_episode(
    data: TensorDictBase, fraction: float, *, generator: torch.Generator | None = None
) -> tuple[TensorDictBase, TensorDictBase]:
    """Split transitions into two disjoint sets by episode: ``(rest, part)`` with ``part`` about ``fraction``.

    Whole episodes go to one side or the other, so the two sets are independent draws of the behaviour law.
    """
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"fraction must lie in (0, 1), got {fraction}.")
    if "episode" not in data.keys():
        raise KeyError("split_by_episode needs an 'episode' entry (collect_transitions writes it).")
    episodes = torch.unique(data["episode"])
    if len(episodes) < 2:
        raise ValueError(f"Need at least 2 episodes to split, got {len(episodes)}.")
    perm = episodes[torch.randperm(len(episodes), generator=generator)]
    n_part = min(max(1, round(fraction * len(episodes))), len(episodes) - 1)
    in_part = torch.isin(data["episode"], perm[:n_part])
    return data[~in_part], data[in_part]


def make_replay_buffer(
    data: TensorDictBase,
    *,
    batch_size: int | None = None,
    storage: str = "lazy",
    scratch_dir: str | os.PathLike | None = None,
) -> TensorDictReplayBuffer:
    """A ``TensorDictReplayBuffer`` holding ``data`` (``storage="lazy"``: in RAM; ``"memmap"``: on disk)."""
    n = data.shape[0]
    if storage == "lazy":
        store = LazyTensorStorage(n)
    elif storage == "memmap":
        store = LazyMemmapStorage(n, scratch_dir=scratch_dir)
    else:
        raise ValueError(f"storage must be 'lazy' or 'memmap', got {storage!r}.")
    rb = TensorDictReplayBuffer(storage=store, batch_size=batch_size)
    rb.extend(data)
    return rb


def _state_action_signature(td: TensorDictBase) -> dict:
    return {
        str(k): (tuple(td.get(k).shape[1:]), str(td.get(k).dtype)) for k in STATE_ACTION_KEYS if k in td.keys(True)
    }


@dataclass
class OfflineDatasets:
    """The three offline sets of the paper, each in its own replay buffer.

    Attributes:
        transitions: ``D``, behaviour transitions for the Bellman residual.
        behaviour_samples: ``S^b``, behaviour state-action samples for the ratio (disjoint from ``D``).
        expert_samples: ``S^e``, expert state-action samples for the ratio.
        metadata: how the data was made (env, policies, sizes, seed); saved with it.
    """

    transitions: TensorDictReplayBuffer
    behaviour_samples: TensorDictReplayBuffer
    expert_samples: TensorDictReplayBuffer
    metadata: dict = field(default_factory=dict)

    def __post_init__(self):
        self.validate()

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_tensordicts(
        cls,
        transitions: TensorDictBase,
        behaviour_samples: TensorDictBase,
        expert_samples: TensorDictBase,
        *,
        metadata: dict | None = None,
        storage: str = "lazy",
        scratch_dir: str | os.PathLike | None = None,
    ) -> "OfflineDatasets":
        for name, td in zip(PARTS, (transitions, behaviour_samples, expert_samples)):
            if td.batch_size.numel() == 0:  # (TensorDict.numel() is 1 for an empty batch)
                raise ValueError(f"The {name} set is empty: collect at least one {name.replace('_', ' ')} sample.")
            if td.ndim != 1:
                raise ValueError(f"The {name} set has batch shape {tuple(td.shape)}: expected a flat set [N].")
        bufs = [
            make_replay_buffer(
                td, storage=storage, scratch_dir=None if scratch_dir is None else Path(scratch_dir) / name
            )
            for name, td in zip(PARTS, (transitions, behaviour_samples, expert_samples))
        ]
        return cls(*bufs, metadata=dict(metadata or {}))

    @classmethod
    def from_behaviour_and_expert(
        cls,
        behaviour: TensorDictBase,
        expert: TensorDictBase,
        *,
        ratio_fraction: float = 0.5,
        generator: torch.Generator | None = None,
        metadata: dict | None = None,
        storage: str = "lazy",
        scratch_dir=None,
    ) -> "OfflineDatasets":
        """Split ``behaviour`` by episode into ``D`` and ``S^b`` (``ratio_fraction`` of its episodes)."""
        transitions, behaviour_samples = split_by_episode(behaviour, ratio_fraction, generator=generator)
        meta = dict(metadata or {})
        meta.setdefault("ratio_fraction", ratio_fraction)
        return cls.from_tensordicts(
            transitions,
            behaviour_samples.select(*STATE_ACTION_KEYS, "episode", strict=False),
            expert,
            metadata=meta,
            storage=storage,
            scratch_dir=scratch_dir,
        )

    # ------------------------------------------------------------------ checks
    def validate(self) -> None:
        """Raise a ``ValueError``/``KeyError`` that says what is wrong with an incomplete or inconsistent set."""
        parts = dict(zip(PARTS, (self.transitions, self.behaviour_samples, self.expert_samples)))
        for name, rb in parts.items():
            if len(rb) == 0:
                raise ValueError(f"The {name} set is empty: collect at least one {name.replace('_', ' ')} sample.")
        content = {name: rb[:] for name, rb in parts.items()}
        missing = [k for k in TRANSITION_KEYS if k not in content["transitions"].keys(True)]
        if missing:
            raise KeyError(f"The transitions set lacks the keys {missing} (expected {list(TRANSITION_KEYS)}).")
        for name in ("behaviour_samples", "expert_samples"):
            lacking = [k for k in STATE_ACTION_KEYS if k not in content[name].keys(True)]
            if lacking:
                raise KeyError(f"The {name} set lacks the keys {lacking} (expected {list(STATE_ACTION_KEYS)}).")
        signatures = {name: _state_action_signature(td) for name, td in content.items()}
        reference = signatures["transitions"]
        for name, sig in signatures.items():
            if sig != reference:
                raise ValueError(
                    f"Incompatible datasets: the {name} set has (shape, dtype) per key {sig}, but the transitions "
                    f"set has {reference}. Expert and behaviour data must come from the same env."
                )

    # ------------------------------------------------------------------ sampling
    def paired_sampler(self, batch_size: int) -> "PairedSampler":
        """A sampler of ratio batches ``TensorDict({"behaviour": [B], "expert": [B]})``."""
        return PairedSampler(self.behaviour_samples, self.expert_samples, batch_size)

    def sizes(self) -> dict[str, int]:
        return {name: len(getattr(self, name)) for name in PARTS}

    def summary(self) -> str:
        s = self.sizes()
        lines = [
            f"D (behaviour transitions for Q): {s['transitions']}",
            f"S^b (behaviour state-actions for the ratio): {s['behaviour_samples']}",
            f"S^e (expert state-actions for the ratio): {s['expert_samples']}",
        ]
        for key in ("behaviour_mean_return", "expert_mean_return"):
            if key in self.metadata:
                lines.append(f"{key}: {self.metadata[key]:.4f}")
        return "\n".join(lines)

    # ------------------------------------------------------------------ disk
    def save(self, path: str | os.PathLike) -> Path:
        """Write the three sets (memory-mapped TensorDicts) and ``metadata.json`` to ``path``."""
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        for name in PARTS:
            getattr(self, name)[:].memmap(path / name)
        meta = {"format_version": FORMAT_VERSION, "sizes": self.sizes(), **self.metadata}
        (path / "metadata.json").write_text(json.dumps(meta, indent=2, default=str))
        return path

    @classmethod
    def load(cls, path: str | os.PathLike, *, storage: str = "lazy", scratch_dir=None) -> "OfflineDatasets":
        """Load what :meth:`save` wrote; missing, corrupt or incompatible data raises an error saying which."""
        path = Path(path)
        if not path.is_dir():
            raise FileNotFoundError(f"No dataset directory at {path} (make one with OfflineDatasets.save).")
        meta_file = path / "metadata.json"
        if not meta_file.is_file():
            raise FileNotFoundError(f"{path} is not a dataset: it has no metadata.json.")
        try:
            meta = json.loads(meta_file.read_text())
        except json.JSONDecodeError as err:
            raise ValueError(f"Corrupt dataset at {path}: metadata.json is not valid JSON ({err}).") from err
        version = meta.pop("format_version", None)
        if version != FORMAT_VERSION:
            raise ValueError(
                f"Incompatible dataset at {path}: format_version {version!r}, this code reads {FORMAT_VERSION}."
            )
        sizes = meta.pop("sizes", {})
        parts = {}
        for name in PARTS:
            part = path / name
            if not part.is_dir():
                raise FileNotFoundError(f"Dataset at {path} is missing its {name!r} part ({part}).")
            try:
                td = TensorDict.load_memmap(part)
            except Exception as err:  # tensordict raises several types on a damaged folder
                raise ValueError(f"Corrupt dataset at {path}: cannot read its {name!r} part ({err}).") from err
            if name in sizes and td.shape[0] != sizes[name]:
                raise ValueError(
                    f"Corrupt dataset at {path}: {name!r} holds {td.shape[0]} samples, metadata says {sizes[name]}."
                )
            parts[name] = td.clone()  # into RAM, detached from the files
        return cls.from_tensordicts(
            parts["transitions"],
            parts["behaviour_samples"],
            parts["expert_samples"],
            metadata=meta,
            storage=storage,
            scratch_dir=scratch_dir,
        )


class PairedSampler:
    """Draws ``TensorDict({"behaviour": S^b batch, "expert": S^e batch})`` through a ``ReplayBufferEnsemble``."""

    def __init__(self, behaviour: TensorDictReplayBuffer, expert: TensorDictReplayBuffer, batch_size: int):
        if batch_size <= 0:
            raise ValueError(f"batch_size must be > 0, got {batch_size}.")
        self.batch_size = int(batch_size)
        self._ensemble = ReplayBufferEnsemble(behaviour, expert, sample_from_all=True, batch_size=2 * self.batch_size)

    def sample(self) -> TensorDict:
        pair = self._ensemble.sample().exclude("index")
        return TensorDict(
            {"behaviour": pair[0].select(*STATE_ACTION_KEYS), "expert": pair[1].select(*STATE_ACTION_KEYS)},
            batch_size=[self.batch_size],
        )


def episode_returns(data: TensorDictBase, *, gamma: float = 1.0) -> torch.Tensor:
    """Per-episode returns ``sum_t gamma^t r_t`` of the *complete* episodes in flat transition data.

    Needs ``"episode"`` ids (as written by :func:`collect_transitions`, transitions of an episode in time order);
    an episode counts only if one of its transitions is ``("next", "done")``, so the partial episode a collector
    stops in does not bias the figure.
    """
    if "episode" not in data.keys():
        raise KeyError("episode_returns needs an 'episode' entry (collect_transitions writes it).")
    ids, inverse = torch.unique(data["episode"], return_inverse=True)
    n = len(ids)
    order = torch.argsort(inverse, stable=True)
    sorted_inv = inverse[order]
    counts = torch.bincount(sorted_inv, minlength=n)
    starts = torch.cumsum(counts, 0) - counts
    t = torch.empty_like(inverse)
    t[order] = torch.arange(len(inverse)) - starts[sorted_inv]
    reward = data["next", "reward"].reshape(-1).double()
    discounted = reward * torch.as_tensor(gamma, dtype=torch.float64) ** t.double()
    returns = torch.zeros(n, dtype=torch.float64).index_add_(0, inverse, discounted)
    done = torch.zeros(n, dtype=torch.bool).index_put_((inverse,), data["next", "done"].reshape(-1), accumulate=True)
    return returns[done]
