"""Offline datasets: collection with torchrl's ``Collector``, the paper's split, replay buffers, save/load.

The paper (Section 3) needs three independent sets:

* ``D`` — behaviour transitions ``(x, a, r, x')`` for the Bellman residual (``transitions``);
* ``S^b`` — behaviour state-action samples for the density ratio (``behaviour_samples``);
* ``S^e`` — expert state-action samples for the density ratio (``expert_samples``).

``D`` and ``S^b`` come from one behaviour collection split by *episode* (so the two sets are disjoint and
independent, as the paper requires ``S`` independent of ``D``). Each set lives in a ``TensorDictReplayBuffer``
over a ``LazyTensorStorage`` (or a ``LazyMemmapStorage`` for data larger than memory); paired ratio batches
``TensorDict({"behaviour": ..., "expert": ...})`` are drawn by :class:`~torchrl_wbrm.data.sampling.PairedSampler`.
"""
from __future__ import annotations

import errno
import hashlib
import json
import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import Collector
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer

from torchrl_wbrm._files import atomic_write
from torchrl_wbrm.keys import EPISODE, METADATA
from torchrl_wbrm.data.sampling import STATE_ACTION_KEYS, PairedSampler

__all__ = [
    "OfflineDatasets",
    "collect_transitions",
    "split_by_episode",
    "check_episodes_in_order",
    "make_replay_buffer",
    "min_behaviour_episodes",
    "FORMAT_VERSION",
    "TRANSITION_KEYS",
    "episode_returns",
    "check_finite",
    "read_saved_dataset",
]

#: 2: metadata.json records every file's dtype, shape, size and SHA-256 (1 had none).
FORMAT_VERSION = 2
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
    data.set(EPISODE, episode + episode_offset)
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
    if EPISODE not in data.keys():
        raise KeyError("split_by_episode needs an 'episode' entry (collect_transitions writes it).")
    episodes = torch.unique(data[EPISODE])
    if len(episodes) < 2:
        raise ValueError(f"Need at least 2 episodes to split, got {len(episodes)}.")
    perm = episodes[torch.randperm(len(episodes), generator=generator)]
    n_part = min(max(1, round(fraction * len(episodes))), len(episodes) - 1)
    in_part = torch.isin(data[EPISODE], perm[:n_part])
    return data[~in_part], data[in_part]


def check_episodes_in_order(data: TensorDictBase, what: str) -> None:
    """Refuse ``data`` unless each episode's rows are contiguous and in time order: one run of rows per episode id,
    and, inside an episode, each row's ``("next", "observation")`` the next row's ``"observation"``. ``what`` names
    the data in the one-line error, which names the first episode that breaks the order.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> obs = torch.tensor([[0.0], [1.0], [2.0], [5.0]])
        >>> td = TensorDict({"observation": obs, "episode": torch.tensor([0, 0, 0, 1]),
        ...                  "next": {"observation": torch.tensor([[1.0], [2.0], [3.0], [6.0]])}}, [4])
        >>> check_episodes_in_order(td, "D")
        >>> check_episodes_in_order(td[torch.tensor([1, 0, 2, 3])], "D")
        Traceback (most recent call last):
        ...
        ValueError: D: episode 0's rows are not in time order (row 0's ("next", "observation") is not row 1's "observation"); each episode's rows must be contiguous and in the order they were collected.
    """
    episode = data[EPISODE].reshape(-1)
    starts = torch.ones_like(episode, dtype=torch.bool)
    starts[1:] = episode[1:] != episode[:-1]
    runs = episode[starts]
    if runs.numel() != torch.unique(runs).numel():
        ids, counts = torch.unique(runs, return_counts=True)
        raise ValueError(f"{what}: episode {int(ids[counts > 1][0])}'s rows are not contiguous; each episode's rows "
                         f"must be contiguous and in the order they were collected.")
    same = ~starts[1:]
    nxt, obs = data["next", "observation"][:-1], data["observation"][1:]
    broken = same & ~(nxt == obs).reshape(nxt.shape[0], -1).all(-1)
    if bool(broken.any()):
        row = int(broken.nonzero()[0])
        raise ValueError(f"{what}: episode {int(episode[row])}'s rows are not in time order (row {row}'s (\"next\", "
                         f"\"observation\") is not row {row + 1}'s \"observation\"); each episode's rows must be "
                         f"contiguous and in the order they were collected.")


def min_behaviour_episodes(ratio_fraction: float) -> int:
    """The fewest behaviour episodes :meth:`OfflineDatasets.from_behaviour_and_expert` can split with
    ``ratio_fraction``: ``S^b`` takes at least one, and ``D`` keeps at least two (a trainer splits ``D`` by episode
    again, into its training and held-out sets). 4 for the default 0.5.

    Examples:
        >>> min_behaviour_episodes(0.5)
        4
    """
    if not 0.0 < ratio_fraction < 1.0:
        raise ValueError(f"ratio_fraction must lie in (0, 1), got {ratio_fraction}.")
    n = 3
    while n - min(max(1, round(ratio_fraction * n)), n - 1) < 2:
        n += 1
    return n


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
        """Split ``behaviour`` by episode into ``D`` and ``S^b`` (``ratio_fraction`` of its episodes).

        ``behaviour`` must hold at least :func:`min_behaviour_episodes` episodes; fewer raise a ``ValueError`` naming
        the dataset (``metadata["behaviour_dataset"]``, where a reader records it) and the minimum.
        """
        meta = dict(metadata or {})
        if EPISODE in behaviour.keys():
            episodes = int(torch.unique(behaviour[EPISODE]).numel())
            needed = min_behaviour_episodes(ratio_fraction)
            if episodes < needed:
                name = meta.get("behaviour_dataset")
                what = f"The behaviour dataset {name!r}" if name else "The behaviour data"
                raise ValueError(
                    f"{what} holds {episodes} episode(s); at least {needed} are needed (with ratio_fraction="
                    f"{ratio_fraction}: S^b takes at least one episode and D keeps at least two, which the trainer "
                    f"splits into its training and held-out sets). Use a behaviour dataset with more episodes."
                )
        transitions, behaviour_samples = split_by_episode(behaviour, ratio_fraction, generator=generator)
        meta.setdefault("ratio_fraction", ratio_fraction)
        return cls.from_tensordicts(
            transitions,
            behaviour_samples.select(*STATE_ACTION_KEYS, EPISODE, strict=False),
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
        for name, td in content.items():
            check_finite(td, f"The {name} set")

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
        """Write the three sets (memory-mapped TensorDicts) and ``metadata.json`` to ``path``.

        ``metadata.json`` records, for every file of every set, its path, dtype, shape, size in bytes and SHA-256,
        so :meth:`load` can verify the data before using it.
        """
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        sets = {name: getattr(self, name)[:] for name in PARTS}
        needed = sum(v.numel() * v.element_size() for td in sets.values() for v in td.values(True, True))
        free = shutil.disk_usage(path).free
        if free < needed + (1 << 20):  # refused before a memory-mapped write runs past the disk's end (SIGBUS)
            raise OSError(errno.ENOSPC, f"Saving the dataset to {path} needs {needed / 2**20:.1f} MiB; the disk holding "
                                        f"it has {free / 2**20:.1f} MiB free. Free space there, or choose another "
                                        f"folder (data_cache=..., out=...).")
        files = {}
        for name in PARTS:
            td = sets[name]
            # written into a folder made fresh for it (nothing under it can be a planted link), then moved into place:
            # an old set, or a link planted under the set's name, is replaced, never written through
            fresh = Path(tempfile.mkdtemp(prefix=f".{name}.", dir=path))
            td.memmap(fresh)
            target = path / name
            if target.is_symlink() or target.is_file():
                target.unlink()
            elif target.exists():
                shutil.rmtree(target)
            os.replace(fresh, target)
            entries = {}
            for key in td.keys(True, True):
                key = key if isinstance(key, tuple) else (key,)
                rel = "/".join((name, *key)) + ".memmap"
                value = td.get(key)
                size, digest = _file_digest(path / rel)
                expected = value.numel() * value.element_size()
                if size != expected:
                    raise RuntimeError(f"Saving {path}: {rel} holds {size} bytes after writing, expected {expected}.")
                entries["/".join(key)] = {
                    "file": rel, "dtype": str(value.dtype), "shape": list(value.shape), "bytes": size, "sha256": digest,
                }
            files[name] = entries
        meta = {"format_version": FORMAT_VERSION, "sizes": self.sizes(), "files": files, **self.metadata}
        text = json.dumps(meta, indent=2, default=str)
        atomic_write(path / METADATA, lambda f: f.write(text.encode()))
        return path

    @staticmethod
    def read_metadata(path: str | os.PathLike) -> dict:
        """The parsed ``metadata.json`` of a saved dataset (its format version checked); the data are not read."""
        path = Path(path)
        if not path.is_dir():
            raise FileNotFoundError(f"No dataset directory at {path} (make one with OfflineDatasets.save).")
        meta_file = path / METADATA
        if not meta_file.is_file():
            raise FileNotFoundError(f"{path} is not a dataset: it has no metadata.json.")
        try:
            meta = json.loads(meta_file.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise ValueError(f"Corrupt dataset at {path}: metadata.json is not valid JSON ({err}).") from err
        if not isinstance(meta, dict):
            raise ValueError(f"Corrupt dataset at {path}: metadata.json holds a {type(meta).__name__}, not an object.")
        version = meta.get("format_version")
        if version != FORMAT_VERSION:
            raise ValueError(
                f"Incompatible dataset at {path}: format_version {version!r}, this code reads {FORMAT_VERSION} "
                f"(version 2 added per-file checksums; re-create the dataset with OfflineDatasets.save)."
            )
        return meta

    @classmethod
    def load(cls, path: str | os.PathLike, *, storage: str = "lazy", scratch_dir=None) -> "OfflineDatasets":
        """Load what :meth:`save` wrote, after verifying every file against ``metadata.json``.

        Files are opened read-only and never padded, truncated or rewritten. A missing file, a size, dtype or shape
        that differs from the metadata, or a SHA-256 that differs from the recorded one raises an error naming the
        file and what was expected and found (``FileNotFoundError`` for a missing file, ``ValueError`` otherwise); so
        does a NaN or infinite value, naming the set, the key, the episode and the step (:func:`read_saved_dataset`).
        """
        meta, parts = read_saved_dataset(path)
        return cls.from_tensordicts(
            parts["transitions"],
            parts["behaviour_samples"],
            parts["expert_samples"],
            metadata=meta,
            storage=storage,
            scratch_dir=scratch_dir,
        )


class HeldRead:
    """One read of files on disk, held for the next reader of the same files, once: a run's data are read and checked
    before anything is written (:class:`~torchrl_wbrm.training.hydra_guard.RunDirGuard`), and its trainer takes that read
    instead of reading the files again. The key holds every file's size and modification time, so a file changed in
    between is read again."""

    def __init__(self) -> None:
        self._key, self._value = None, None

    def take(self, key):
        """The value held under ``key`` (once), or ``None``."""
        if self._key is None or key != self._key:
            return None
        value, self._key, self._value = self._value, None, None
        return value

    def hold(self, key, value) -> None:
        """Hold ``value`` under ``key`` (replacing whatever was held)."""
        self._key, self._value = key, value


def files_key(*paths: str | os.PathLike) -> tuple:
    """Which files ``paths`` hold, as they are now: each file's path, size and modification time (a folder's files,
    recursively), for :class:`HeldRead`."""
    out = []
    for path in paths:
        path = Path(path).resolve()
        files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
        for file in files:
            stat = file.stat()
            out.append((str(file), stat.st_size, stat.st_mtime_ns))
    return tuple(out)


#: The largest magnitude a number of the data may have: its square, and so every squared loss on it, stays finite in
#: float32 (``sqrt(3.4e38)``, about ``1.8e19``).
MAX_MAGNITUDE = float(torch.finfo(torch.float32).max) ** 0.5


def first_non_finite_row(td: TensorDictBase) -> tuple[str, int, float] | None:
    """The first row of ``td`` (a flat set) holding a NaN or infinite number, or one beyond :data:`MAX_MAGNITUDE`
    (whose square overflows float32), as ``(key, row, value)`` (the first such key, in key order, of the first such
    row), or ``None``."""
    first = None
    for key, value in td.items(True, True):
        if not value.is_floating_point() or value.ndim == 0:
            continue
        flat = value.reshape(value.shape[0], -1)
        bad = ~torch.isfinite(flat) | (flat.double().abs() > MAX_MAGNITUDE)
        rows = bad.any(-1).nonzero()
        if rows.numel() and (first is None or int(rows[0]) < first[1]):
            row = int(rows[0])
            entry = value.reshape(value.shape[0], -1)[row][bad[row]][0]
            first = ("/".join(key) if isinstance(key, tuple) else key, row, float(entry))
    return first


def check_finite(td: TensorDictBase, where: str) -> None:
    """Refuse a set with a NaN or infinite number: a ``ValueError`` ``"<where>: episode E, step S: <key> is nan
    ..."`` naming the first such row's episode and its step within the episode (its rank among that episode's rows,
    which are in time order), or the row where the set has no ``"episode"`` ids."""
    found = first_non_finite_row(td)
    if found is None:
        return
    key, row, value = found
    if EPISODE in td.keys():
        episodes = td.get(EPISODE)
        episode = int(episodes[row])
        step = int((episodes[:row] == episode).sum())
        where_in = f"episode {episode}, step {step} (row {row})"
    else:
        where_in = f"row {row}"
    if math.isfinite(value):
        raise ValueError(f"{where}: {where_in}: {key!r} is {value:.3g}, beyond {MAX_MAGNITUDE:.3g} in magnitude: its "
                         f"square overflows float32, so every loss on it would (fix or drop that episode, or rescale "
                         f"the data, then save the dataset again).")
    raise ValueError(f"{where}: {where_in}: {key!r} is {value}; every observation, action and reward must be finite "
                     f"(fix or drop that episode, then save the dataset again).")


#: a saved dataset read and verified before a run starts, for its trainer (:func:`read_saved_dataset`)
_HELD_SAVED = HeldRead()


def read_saved_dataset(path: str | os.PathLike, *, keep: bool = False) -> tuple[dict, dict[str, TensorDict]]:
    """The metadata and the three sets of the dataset :meth:`OfflineDatasets.save` wrote to ``path``: every file
    verified against ``metadata.json`` (size, dtype, shape, SHA-256) and every number checked finite
    (:func:`check_finite`, the error naming the dataset, the set, the episode, the step and the key).

    ``keep=True`` holds what was read for the next call on the same, unchanged files (once): a run checks its data
    before it writes anything, and its trainer's :meth:`OfflineDatasets.load` then reads them once only.
    """
    path = Path(path)
    key = (str(path.resolve()), files_key(path)) if path.is_dir() else None
    held = _HELD_SAVED.take(key) if key is not None else None
    if held is not None:
        return dict(held[0]), dict(held[1])
    meta = dict(OfflineDatasets.read_metadata(path))
    meta.pop("format_version")
    sizes = meta.pop("sizes", {})
    files = meta.pop("files", None)
    if not isinstance(files, dict):
        raise ValueError(f"Corrupt dataset at {path}: metadata.json lists no 'files' (their checksums).")
    parts = {}
    for name in PARTS:
        part = path / name
        if not part.is_dir():
            raise FileNotFoundError(f"Dataset at {path} is missing its {name!r} part ({part}).")
        entries = files.get(name)
        if not isinstance(entries, dict) or not entries:
            raise ValueError(f"Corrupt dataset at {path}: metadata.json lists no files for its {name!r} part.")
        parts[name] = _read_verified_part(path, name, entries, sizes.get(name))
        check_finite(parts[name], f"Dataset at {path}, its {name} set")
    if keep:
        _HELD_SAVED.hold(key, (meta, parts))
    return dict(meta), dict(parts)


def _file_digest(file: Path, chunk: int = 1 << 20) -> tuple[int, str]:
    """``(size in bytes, SHA-256 hex digest)`` of ``file``, read in chunks."""
    h = hashlib.sha256()
    size = 0
    with open(file, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
            size += len(block)
    return size, h.hexdigest()


def _torch_dtype(name: str, where: str) -> torch.dtype:
    dtype = getattr(torch, str(name).removeprefix("torch."), None)
    if not isinstance(dtype, torch.dtype):
        raise ValueError(f"{where}: unknown dtype {name!r} in metadata.json.")
    return dtype


def _read_verified_part(root: Path, name: str, entries: dict, expected_rows) -> TensorDict:
    """One set, read file by file (read-only) and checked against its recorded size, dtype, shape and SHA-256."""
    where = f"Corrupt dataset at {root}"
    values = {}
    rows = None
    for key, entry in entries.items():
        try:
            rel, dtype_name, shape = entry["file"], entry["dtype"], tuple(int(n) for n in entry["shape"])
            expected_bytes, expected_hash = int(entry["bytes"]), str(entry["sha256"])
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"{where}: the metadata of {name}/{key} is incomplete ({err!r}).") from err
        dtype = _torch_dtype(dtype_name, f"{where}, file {rel}")
        if not shape:
            raise ValueError(f"{where}: file {rel} has an empty shape in metadata.json.")
        if rows is None:
            rows = shape[0]
            if expected_rows is not None and rows != expected_rows:
                raise ValueError(f"{where}: {name!r} holds {rows} samples, metadata says {expected_rows}.")
        elif shape[0] != rows:
            raise ValueError(f"{where}: file {rel} has {shape[0]} rows, the other files of {name!r} have {rows}.")
        numel = math.prod(shape)
        itemsize = torch.empty((), dtype=dtype).element_size()
        if numel * itemsize != expected_bytes:
            raise ValueError(
                f"{where}: metadata.json says file {rel} is {dtype_name} of shape {list(shape)} "
                f"({numel * itemsize} bytes) but also that it has {expected_bytes} bytes."
            )
        file = root / rel
        if not file.is_file():
            raise FileNotFoundError(f"{where}: file {rel} is missing (expected {expected_bytes} bytes).")
        found_bytes = file.stat().st_size
        if found_bytes != expected_bytes:
            raise ValueError(
                f"{where}: file {rel} has {found_bytes} bytes, expected {expected_bytes} "
                f"({dtype_name}, shape {list(shape)}). The file is truncated or overwritten; it was not changed."
            )
        with open(file, "rb") as f:  # read-only: nothing on disk is touched
            raw = f.read()
        found_hash = hashlib.sha256(raw).hexdigest()
        if found_hash != expected_hash:
            raise ValueError(
                f"{where}: file {rel} has SHA-256 {found_hash}, expected {expected_hash} "
                f"(same size, different content: the file is damaged)."
            )
        values[tuple(key.split("/"))] = torch.frombuffer(bytearray(raw), dtype=dtype).reshape(shape)
    td = TensorDict({}, batch_size=[rows])
    for key, value in values.items():
        td.set(key, value)
    return td


def episode_returns(data: TensorDictBase, *, gamma: float = 1.0) -> torch.Tensor:
    """Per-episode returns ``sum_t gamma^t r_t`` of the *complete* episodes in flat transition data.

    Needs ``"episode"`` ids (as written by :func:`collect_transitions`, transitions of an episode in time order);
    an episode counts only if one of its transitions is ``("next", "done")``, so the partial episode a collector
    stops in does not bias the figure.
    """
    if EPISODE not in data.keys():
        raise KeyError("episode_returns needs an 'episode' entry (collect_transitions writes it).")
    ids, inverse = torch.unique(data[EPISODE], return_inverse=True)
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
