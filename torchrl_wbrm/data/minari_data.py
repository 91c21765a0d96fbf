"""Minari datasets in and out: D, S^b and S^e from two local Minari datasets, and any transitions to a Minari dataset.

Minari (the Farama Foundation's successor of D4RL) stores offline-RL data as episodes of ``observations``
(``T + 1`` rows), ``actions``, ``rewards``, ``terminations`` and ``truncations`` (``T`` rows each), with the
observation and action spaces and, when the data came from a registered gymnasium env, that env's spec.

:func:`make_minari_datasets` reads two such datasets, an *expert* one and a *behaviour* one:

* ``S^e`` is every state-action of the expert dataset, or of ``expert_episodes`` of its episodes drawn by the run's
  seed (:func:`draw_expert_episodes`: each seed draws its own few demonstrations);
* the behaviour dataset is split *by episode* into ``D`` (transitions for Q) and ``S^b`` (state-actions for the
  ratio), as for the project's own data (:meth:`OfflineDatasets.from_behaviour_and_expert`).

A dataset is named by its Minari id (looked up under ``MINARI_DATASETS_PATH``, else ``~/.minari/datasets``, or
``MinariDataConfig.data_path``) or by a local path (the dataset's folder or its ``data/`` folder). Nothing is ever
downloaded: a dataset that is not on disk is a ``FileNotFoundError`` naming the id and the path searched. Two
datasets with different observation or action spaces, or recorded on different envs, are a ``ValueError`` naming
both. Nothing is coerced: a NaN or infinite observation, action or reward, an action outside the action space or an
empty dataset is a one-line ``ValueError`` naming the dataset, the episode, the first offending step and the key
(:func:`check_minari_data`, which the recipe runs before it writes anything).

Spaces: a ``Box`` observation of any shape and a one-dimensional ``Box`` or a ``Discrete`` action. An observation
of shape ``(d1, d2, ...)`` (a grid, an image) is read flattened (row-major, ``d1 d2 ...`` float32 numbers), and
the evaluation env flattens and casts its observation the same way (torchrl's ``FlattenObservation`` and
``DTypeCastTransform``), so the networks see one vector in training and in evaluation. A ``Discrete(n)`` action is
stored one-hot (``n`` floats), so the ratio network sees a vector as for a box; ``metadata["discrete_actions"] = n``
makes ``wbrm`` / ``brm`` fit a Q head over the ``n`` actions (``algos.base.discrete_bellman_residual_algo``) and
gives ``dqn`` the ``n`` actions as its grid (:class:`OneHotActions`); the evaluation env steps gym with the
``argmax`` of the policy's output (:func:`make_minari_eval_env`).

Reading uses Minari's own reader (``MinariDataset.iterate_episodes``). torchrl's ``MinariExperienceReplay`` does the
same conversion, but it reads only ids under ``MINARI_DATASETS_PATH`` and writes a second, memory-mapped copy of
every dataset under its own cache folder; the datasets here are read once into memory, so it is not used. The
transitions read are kept in the dataset's own ``data/`` folder for later runs (:func:`read_dataset_transitions`,
``env.minari.cache``).

:func:`write_minari_dataset` writes episodes as a Minari dataset through ``minari.create_dataset_from_buffers``
with ``EpisodeBuffer`` objects, which needs only ``minari[hdf5]`` (``minari.DataCollector`` would need jax, the
``minari[create]`` extra). :func:`transitions_to_episodes` turns this project's flat transitions into those
episodes (``recipes/make_dataset.py format=minari``).
"""
from __future__ import annotations

import contextlib
import json
import io
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Optional

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_wbrm._console import route_mujoco_warnings
from torchrl_wbrm._files import atomic_write
from torchrl_wbrm.keys import EPISODE
from torchrl_wbrm.data.datasets import (MAX_MAGNITUDE, HeldRead, OfflineDatasets, episode_returns, files_key,
                                        first_non_finite_row, min_behaviour_episodes)

__all__ = [
    "MinariDataConfig",
    "draw_expert_episodes",
    "make_minari_datasets",
    "check_minari_data",
    "make_minari_eval_env",
    "OneHotActions",
    "minari_data_root",
    "minari_discrete_action",
    "resolve_minari_dataset",
    "check_new_minari_ids",
    "delete_minari_datasets",
    "read_minari_transitions",
    "read_dataset_transitions",
    "TRANSITIONS_CACHE",
    "write_minari_dataset",
    "transitions_to_episodes",
]


@dataclass
class MinariDataConfig:
    """Which Minari datasets (``env=minari``; see ``configs/env/minari.yaml``).

    Attributes:
        expert: the expert dataset (-> ``S^e``): a Minari id (``"pendulum/expert-v0"``) or a local path.
        behaviour: the behaviour dataset (-> ``D`` and ``S^b``, split by episode): an id or a path.
        eval_env: the gymnasium id to evaluate on (``None``: the dataset's own evaluation env, else the env it was
            collected on, as recorded in the expert dataset).
        ratio_fraction: share of the behaviour episodes that go to ``S^b``.
        data_path: where ids are looked up (``None``: ``MINARI_DATASETS_PATH``, else ``~/.minari/datasets``).
        expert_episodes: how many of the expert dataset's episodes make ``S^e`` (``None``: all), drawn without
            replacement by the run's seed (:func:`draw_expert_episodes`), so each seed of a multi-seed run draws its
            own; more than the dataset holds is refused naming the key and the count.
        cache: keep each dataset's transitions, once read and checked, in its ``data/`` folder
            (:data:`TRANSITIONS_CACHE`), so later runs read one file instead of every episode again (the Minari
            tutorial gives the times). The cache is
            used only while the dataset's own files are unchanged (sizes and modification times), loaded with
            ``weights_only=True`` and checked again; a folder that cannot be written is read uncached.
    """

    expert: str = ""
    behaviour: str = ""
    eval_env: Optional[str] = None
    ratio_fraction: float = 0.5
    data_path: Optional[str] = None
    expert_episodes: Optional[int] = None
    cache: bool = True


def minari_data_root(data_path: str | os.PathLike | None = None) -> Path:
    """The folder Minari ids are looked up in (nothing is created)."""
    if data_path:  # absolute: Minari's writer mis-joins a relative data path
        return Path(data_path).expanduser().absolute()
    env_path = os.environ.get("MINARI_DATASETS_PATH")
    return Path(env_path).expanduser().absolute() if env_path else Path.home() / ".minari" / "datasets"


def _is_data_dir(path: Path) -> bool:
    return path.is_dir() and (path / "metadata.json").is_file() and any(path.glob("main_data.*"))


def resolve_minari_dataset(ref: str, data_path: str | os.PathLike | None = None) -> Path:
    """The ``data/`` folder of the Minari dataset ``ref`` (an id or a local path); never downloads.

    Raises ``FileNotFoundError`` naming the id (or path) and the Minari data path searched.
    """
    if not ref:
        raise ValueError("No Minari dataset given: set env.minari.expert and env.minari.behaviour (ids or paths).")
    path = Path(ref).expanduser()
    for candidate in (path / "data", path):
        if _is_data_dir(candidate):
            return candidate
    root = minari_data_root(data_path)
    for candidate in (root / ref / "data", root / ref):
        if _is_data_dir(candidate):
            return candidate
    raise FileNotFoundError(
        f"Minari dataset {ref!r} not found: neither a local dataset folder nor {root / ref / 'data'} "
        f"(Minari data path {root}; set MINARI_DATASETS_PATH or env.minari.data_path). Nothing is downloaded at run "
        f"time: fetch it once with `minari download {ref}` where there is a network, or give the dataset's folder."
    )


def _inside(folder: Path, root: Path) -> Path | None:
    """``None`` if ``folder`` lies inside ``root`` once every link on the way is resolved, else where it leads."""
    real, real_root = Path(os.path.realpath(folder)), Path(os.path.realpath(root))
    return None if real == real_root or real_root in real.parents else real


def check_new_minari_ids(dataset_ids: Iterable[str], data_path: str | os.PathLike | None = None, *,
                         setting: str, overwrite: bool = False) -> list[Path]:
    """Refuse to write over existing Minari datasets, before anything is collected.

    Each of ``dataset_ids`` must be a valid Minari id (``namespace/name-vN``). If any already exists under the Minari
    data path (``data_path``, see :func:`minari_data_root`), a ``FileExistsError`` names the id, its folder, the data
    path and ``setting``: the writer's setting that picks other ids (e.g. ``"minari_namespace=<name>"``).
    ``overwrite=True`` checks the ids' syntax only. Returns the ids' folders.

        >>> import tempfile
        >>> folders = check_new_minari_ids(["demo/expert-v0"], tempfile.mkdtemp(), setting="--namespace")
        >>> folders[0].parts[-2:]
        ('demo', 'expert-v0')
    """
    from minari.dataset.minari_dataset import parse_dataset_id

    root = minari_data_root(data_path)
    folders = []
    for dataset_id in dataset_ids:
        try:
            parse_dataset_id(dataset_id)
        except ValueError as err:
            raise ValueError(f"{dataset_id!r} is not a Minari dataset id (namespace/name-vN): set {setting} to "
                             f"letters, digits, '_', '-' and '/'. ({err})") from None
        folder = root / dataset_id
        inside = _inside(folder, root)
        if inside is not None:
            raise ValueError(f"The Minari dataset {dataset_id!r} would be written at {inside}, outside the Minari data "
                             f"path {root} (a link on the way leads out); nothing was written. Choose other ids with "
                             f"{setting}, or another data path.")
        if folder.exists() and not overwrite:
            raise FileExistsError(
                f"The Minari dataset {dataset_id!r} already exists ({folder}, Minari data path {root}); nothing was "
                f"collected. Choose other ids with {setting}, another data path, or delete that dataset.")
        folders.append(folder)
    return folders


def delete_minari_datasets(dataset_ids: Iterable[str], data_path: str | os.PathLike | None = None) -> list[str]:
    """Delete those of ``dataset_ids`` that exist under the Minari data path (``minari.delete_dataset``); returns
    the ids deleted."""
    import minari

    root = minari_data_root(data_path)
    deleted = []
    for dataset_id in dataset_ids:
        if (root / dataset_id).exists():
            with _minari_path(root), contextlib.redirect_stdout(io.StringIO()):  # its own "deleted!" line
                minari.delete_dataset(dataset_id)
            deleted.append(dataset_id)
    return deleted


def _open(ref: str, data_path=None):
    """The ``MinariDataset`` ``ref``; a dataset whose files cannot be read (a truncated ``metadata.json`` or HDF5
    file) is a one-line ``ValueError`` naming the dataset and its folder."""
    from minari.dataset.minari_dataset import MinariDataset

    path = resolve_minari_dataset(ref, data_path)
    try:
        return MinariDataset(str(path))
    except (ValueError, OSError, KeyError, TypeError, json.JSONDecodeError) as err:
        raise ValueError(_damaged(ref, path, err)) from None


def _damaged(ref: str, path: Path, err: BaseException) -> str:
    first = " ".join(str(err).split())[:200] or type(err).__name__
    return (f"Minari dataset {ref!r} ({path}) cannot be read: its files are damaged or truncated ({type(err).__name__}: "
            f"{first}); write or download it again.")


def _check_given(data: MinariDataConfig) -> None:
    """A ``ValueError`` naming the dataset keys ``data`` leaves empty."""
    if not data.expert or not data.behaviour:
        missing = [f"env.minari.{k}" for k in ("expert", "behaviour") if not getattr(data, k)]
        raise ValueError(f"No Minari dataset given in {' and '.join(missing)}: env=minari reads two datasets; set "
                         f"env.minari.expert=<id or path> and env.minari.behaviour=<id or path>.")


def minari_discrete_action(data: MinariDataConfig) -> bool:
    """Whether the action space of ``data``'s expert dataset is a ``Discrete`` (its metadata only, no steps read)."""
    _check_given(data)
    from gymnasium import spaces

    return isinstance(_open(data.expert, data.data_path).action_space, spaces.Discrete)


def _check_spaces(observation_space, action_space, where: str) -> None:
    from gymnasium import spaces

    if not isinstance(observation_space, spaces.Box):
        raise ValueError(f"{where}: the observation space is {observation_space}; only a Box (of any shape) is "
                         f"supported.")
    if not isinstance(action_space, (spaces.Box, spaces.Discrete)):
        raise ValueError(f"{where}: the action space is {action_space}; only a Box or a Discrete is supported.")
    if isinstance(action_space, spaces.Box) and not (np.isfinite(action_space.low).all()
                                                     and np.isfinite(action_space.high).all()):
        raise ValueError(f"{where}: the action space {action_space} is unbounded; actions are scaled to and sampled "
                         f"from a bounded Box, so record the env's finite action bounds in the dataset.")


def _action_tensor(actions: np.ndarray, action_space) -> torch.Tensor:
    from gymnasium import spaces

    if isinstance(action_space, spaces.Discrete):
        index = torch.as_tensor(np.asarray(actions).reshape(-1).astype(np.int64)) - int(action_space.start)
        return torch.nn.functional.one_hot(index, int(action_space.n)).float()
    a = torch.as_tensor(np.asarray(actions, dtype=np.float32))
    return a.reshape(a.shape[0], -1)


def _first_non_finite(values: np.ndarray) -> int | None:
    """The first row (step) of ``values`` holding a NaN or an infinity, or ``None``."""
    if values.dtype.kind not in "fc":  # integers and booleans are finite
        return None
    bad = ~np.isfinite(values.reshape(values.shape[0], -1)).all(-1)
    return int(np.argmax(bad)) if bad.any() else None


def _first_too_large(values: np.ndarray) -> int | None:
    """The first row (step) of ``values`` holding a number beyond :data:`MAX_MAGNITUDE`, or ``None``."""
    if values.dtype.kind not in "fciu" or not values.size:
        return None
    big = (np.abs(values.reshape(values.shape[0], -1).astype(np.float64)) > MAX_MAGNITUDE).any(-1)
    return int(np.argmax(big)) if big.any() else None


def _flat_bounds(space) -> tuple[np.ndarray, np.ndarray]:
    """A ``Box``'s ``low`` and ``high``, broadcast to its shape and read flat (row-major), as float64."""
    return tuple(np.broadcast_to(bound, space.shape).reshape(-1).astype(np.float64) for bound in (space.low, space.high))


def _check_observation_range(observations: np.ndarray, space, name: str, episode: int) -> None:
    """Refuse observations far outside the dataset's declared observation ``space`` (a ``Box``): beyond its finite
    bounds by more than the bounds' own width (a gross mismatch, such as observations recorded 100× the env's scale),
    naming the dataset, the episode and the first such step. Observations slightly outside pass."""
    from gymnasium import spaces

    if not isinstance(space, spaces.Box) or observations.dtype.kind not in "fiu" or not observations.size:
        return
    low, high = _flat_bounds(space)
    flat = observations.reshape(observations.shape[0], -1).astype(np.float64)
    if flat.shape[1] != low.size:
        return  # the shape is refused by the reader, naming it
    finite = np.isfinite(low) & np.isfinite(high)
    width = np.where(finite, high - low, 0.0)
    outside = (finite & ((flat < low - width) | (flat > high + width))).any(-1)
    if outside.any():
        step = int(np.argmax(outside))
        raise ValueError(f"{name}: episode {episode}, step {step}: the observation {flat[step].tolist()} lies far "
                         f"outside the dataset's observation space {space} (beyond its bounds by more than their "
                         f"width); the data and the env they declare do not match (fix the space or the data).")


def _check_episode(episode, action_space, name: str) -> None:
    """Refuse an episode with a NaN or infinite observation, action or reward, or an action outside
    ``action_space``: a ``ValueError`` naming the dataset (``name``), the episode, the first such step and the key."""
    from gymnasium import spaces

    where = f"{name}: episode {episode.id}"
    arrays = {}
    for key in ("observations", "actions", "rewards"):
        values = np.asarray(getattr(episode, key))
        if values.dtype.kind not in "fciub":
            raise ValueError(f"{where}: {key} have dtype {values.dtype}; numbers are expected.")
        step = _first_non_finite(values) if values.ndim else None
        if step is not None:
            raise ValueError(f"{where}, step {step}: {key} hold {values[step].tolist()}; every observation, action and "
                             f"reward must be finite (fix or drop that episode).")
        step = _first_too_large(values) if values.ndim else None
        if step is not None:
            raise ValueError(f"{where}, step {step}: {key} hold {values[step].tolist()}, beyond {MAX_MAGNITUDE:.3g} in "
                             f"magnitude: its square overflows float32, so every loss on it would (fix or drop that "
                             f"episode, or rescale the data).")
        arrays[key] = values
    if arrays["rewards"].size:
        total = np.abs(arrays["rewards"].astype(np.float64)).sum()
        if total > MAX_MAGNITUDE:
            raise ValueError(f"{where}: its rewards sum to {total:.3g} in magnitude, beyond {MAX_MAGNITUDE:.3g}: the "
                             f"episode's return and every value on it overflow float32 (rescale the rewards).")
    actions, steps = arrays["actions"], len(arrays["rewards"])
    if actions.shape[:1] != (steps,):
        raise ValueError(f"{where}: {actions.shape[0] if actions.ndim else 0} actions for {steps} rewards; one "
                         f"action per step is expected.")
    if isinstance(action_space, spaces.Discrete):
        if actions.size != steps:
            raise ValueError(f"{where}: actions of shape {actions.shape[1:]} for the action space {action_space}; "
                             f"one integer per step is expected.")
        flat = actions.reshape(steps)
        start, n = int(action_space.start), int(action_space.n)
        outside = (flat != np.round(flat)) | (flat < start) | (flat >= start + n)
    else:
        size = int(np.prod(action_space.shape))
        if actions.size != steps * size:
            raise ValueError(f"{where}: actions of shape {actions.shape[1:]} for the action space {action_space}; "
                             f"{size} number(s) per step are expected.")
        flat = actions.reshape(steps, size).astype(np.float64)
        low, high = _flat_bounds(action_space)
        outside = ((flat < low) | (flat > high)).any(-1)
    if outside.any():
        step = int(np.argmax(outside))
        raise ValueError(f"{where}, step {step}: the action {actions[step].tolist()} lies outside the dataset's action "
                         f"space {action_space}; every action must lie in it.")


def read_minari_transitions(dataset, *, episode_offset: int = 0, name: str | None = None) -> TensorDict:
    """Every step of a ``MinariDataset`` as flat transitions in this project's layout (``[N]``, float32).

    Keys: ``observation``, ``action`` (one-hot for a ``Discrete`` space), ``("next", "observation" | "reward" |
    "done" | "terminated" | "truncated")`` and an integer ``"episode"`` (the Minari episode id plus
    ``episode_offset``).

    Nothing is coerced: a NaN or infinite observation, action or reward, an action outside the dataset's action space
    or a dataset with no steps is a ``ValueError`` naming the dataset (``name``, default its Minari id), the episode,
    the first offending step and the key.
    """
    name = name or f"Minari dataset {dataset.spec.dataset_id!r}"
    parts = []
    for episode in _episodes_of(dataset, name):
        steps = len(episode.rewards)
        if steps == 0:
            continue
        _check_episode(episode, dataset.action_space, name)
        _check_observation_range(np.asarray(episode.observations), dataset.observation_space, name, episode.id)
        obs = torch.as_tensor(np.asarray(episode.observations, dtype=np.float32))
        if tuple(obs.shape[1:]) != tuple(dataset.observation_space.shape):
            raise ValueError(f"{name}: episode {episode.id} has observations of shape {tuple(obs.shape[1:])}, but the "
                             f"dataset's observation space is {dataset.observation_space}.")
        obs = obs.reshape(obs.shape[0], -1)  # row-major, as the evaluation env's FlattenObservation
        if obs.shape[0] != steps + 1:
            raise ValueError(f"{name}: episode {episode.id} has {obs.shape[0]} observations for {steps} steps.")
        terminated = torch.as_tensor(np.asarray(episode.terminations, dtype=bool)).reshape(steps, 1)
        truncated = torch.as_tensor(np.asarray(episode.truncations, dtype=bool)).reshape(steps, 1)
        parts.append(TensorDict({
            "observation": obs[:-1],
            "action": _action_tensor(episode.actions, dataset.action_space),
            EPISODE: torch.full((steps,), int(episode.id) + episode_offset, dtype=torch.int64),
            "next": {
                "observation": obs[1:],
                "reward": torch.as_tensor(np.asarray(episode.rewards, dtype=np.float32)).reshape(steps, 1),
                "terminated": terminated,
                "truncated": truncated,
                "done": terminated | truncated,
            },
        }, batch_size=[steps]))
    if not parts:
        raise ValueError(f"{name} holds no steps ({dataset.total_episodes} episodes): it is empty; give a dataset with "
                         f"data.")
    return torch.cat(parts, 0)


#: the file, in a Minari dataset's ``data/`` folder, holding its transitions as read and checked
#: (:func:`read_dataset_transitions`, ``env.minari.cache``)
TRANSITIONS_CACHE = "torchrl_wbrm_transitions.pt"
#: the layout of :data:`TRANSITIONS_CACHE`; a file of another is read again from the dataset
_CACHE_FORMAT = 1


def _dataset_files(data_dir: Path) -> list[Path]:
    """The files of a Minari dataset's ``data/`` folder, its transitions cache (and the cache's temporary files)
    left out."""
    return sorted(p for p in Path(data_dir).rglob("*")
                  if p.is_file() and not p.name.startswith(TRANSITIONS_CACHE))


def _files_stamp(data_dir: Path) -> list[list]:
    """Each file of the dataset as it is now (:func:`files_key`), named within its folder (a moved dataset keeps its
    cache)."""
    data_dir = Path(data_dir).resolve()
    return [[str(Path(f).relative_to(data_dir)), size, mtime] for f, size, mtime in files_key(*_dataset_files(data_dir))]


def _cached_transitions(path: Path, stamp: list, dataset) -> TensorDict | None:
    """The transitions :data:`TRANSITIONS_CACHE` at ``path`` holds for the dataset's files as ``stamp`` describes
    them, or ``None`` where it holds none, is of another layout or another version of the files, or does not hold
    what a read of the dataset would (keys, shapes, dtypes, finite values, actions in the action space)."""
    from gymnasium import spaces

    try:
        saved = torch.load(path, weights_only=True, mmap=True)
    except Exception:  # noqa: BLE001 (a missing, truncated or foreign file: read the dataset instead)
        return None
    if not isinstance(saved, dict) or saved.get("format") != _CACHE_FORMAT or saved.get("files") != stamp:
        return None
    try:
        rows = int(saved["rows"])
        td = TensorDict(saved["transitions"], batch_size=[rows])
    except Exception:  # noqa: BLE001
        return None
    expected = {"observation", "action", EPISODE, ("next", "observation"), ("next", "reward"), ("next", "done"),
                ("next", "terminated"), ("next", "truncated")}
    if set(td.keys(True, True)) != expected or rows <= 0:
        return None
    obs = int(np.prod(dataset.observation_space.shape))
    action_space = dataset.action_space
    actions = int(action_space.n) if isinstance(action_space, spaces.Discrete) else int(np.prod(action_space.shape))
    shapes = {"observation": (rows, obs), ("next", "observation"): (rows, obs), "action": (rows, actions),
              EPISODE: (rows,), ("next", "reward"): (rows, 1), ("next", "done"): (rows, 1),
              ("next", "terminated"): (rows, 1), ("next", "truncated"): (rows, 1)}
    dtypes = {EPISODE: torch.int64, ("next", "done"): torch.bool, ("next", "terminated"): torch.bool,
              ("next", "truncated"): torch.bool}
    for key, shape in shapes.items():
        value = td.get(key)
        if tuple(value.shape) != shape or value.dtype != dtypes.get(key, torch.float32):
            return None
    if first_non_finite_row(td) is not None:
        return None
    if not isinstance(action_space, spaces.Discrete):
        low, high = (torch.from_numpy(bound) for bound in _flat_bounds(action_space))
        action = td["action"].double()
        if bool(((action < low) | (action > high)).any()):
            return None
    try:  # observations far outside the declared space, as the episodes' read refuses them
        _check_observation_range(td["observation"].numpy(), dataset.observation_space, "", 0)
    except ValueError:
        return None
    return td


def read_dataset_transitions(dataset, data_dir: str | os.PathLike, *, name: str | None = None,
                             cache: bool = True) -> TensorDict:
    """:func:`read_minari_transitions` of the Minari dataset in ``data_dir``, kept in that folder for the next read.

    With ``cache``, a :data:`TRANSITIONS_CACHE` made from the dataset's files as they are now (each file's size and
    modification time) is loaded instead of the episodes (``weights_only=True``) and checked again: its keys, shapes
    and dtypes, finite values and actions in the action space; one of other files, or that fails a check, is read
    again from the dataset and replaced. After a read, the transitions are written there atomically; a folder that
    cannot be written leaves the dataset uncached (the read stands). Without ``cache`` nothing is read or written
    but the dataset.
    """
    data_dir = Path(data_dir)
    if not cache:
        return read_minari_transitions(dataset, name=name)
    path = data_dir / TRANSITIONS_CACHE
    stamp = _files_stamp(data_dir)
    held = _cached_transitions(path, stamp, dataset) if path.is_file() else None
    if held is not None:
        return held.clone()  # out of the mapped file: the caller may change its copy
    td = read_minari_transitions(dataset, name=name)
    saved = {"format": _CACHE_FORMAT, "files": stamp, "rows": td.batch_size[0], "transitions": td.to_dict()}
    try:
        atomic_write(path, lambda f: torch.save(saved, f), tmp=path.with_name(f"{path.name}.{os.getpid()}.tmp"))
    except OSError:  # a read-only dataset folder: the read stands, uncached
        pass
    return td


def _episodes_of(dataset, name: str):
    """``dataset.iterate_episodes()``, a file that cannot be read (a truncated HDF5) a one-line ``ValueError``."""
    episodes = iter(dataset.iterate_episodes())
    while True:
        try:
            episode = next(episodes)
        except StopIteration:
            return
        except (OSError, KeyError, ValueError, TypeError) as err:
            first = " ".join(str(err).split())[:200] or type(err).__name__
            raise ValueError(f"{name}: its data cannot be read: the files are damaged or truncated "
                             f"({type(err).__name__}: {first}); write or download the dataset again.") from None
        yield episode


def _make_gym_env(spec):
    """``gymnasium.make(spec)`` (an id or an ``EnvSpec``), a MuJoCo env's warnings routed to Python's
    (:func:`~torchrl_wbrm._console.route_mujoco_warnings`: nothing is written to ``MUJOCO_LOG.TXT``)."""
    import gymnasium as gym

    entry = getattr(spec, "entry_point", None)
    if entry is None and isinstance(spec, str):
        try:
            entry = gym.spec(spec).entry_point
        except gym.error.Error:  # an unknown id: gymnasium.make says so below
            entry = None
    if isinstance(entry, str) and "mujoco" in entry:
        route_mujoco_warnings()
    return gym.make(spec)


def _space_text(space) -> str:
    return repr(space)


#: the datasets a run read and checked before it wrote anything, for its trainer (:func:`check_minari_data`)
_HELD_PAIR = HeldRead()


def _read_pair(data: MinariDataConfig) -> tuple[tuple, tuple]:
    """``(key, (expert dataset, behaviour dataset, expert transitions, behaviour transitions))``, every check of
    :func:`check_minari_data` but the episode count passed: the read a run's check held (:data:`_HELD_PAIR`, under
    ``key``, which names the files as they are now), or a new one."""
    _check_given(data)
    paths = [resolve_minari_dataset(ref, data.data_path) for ref in (data.expert, data.behaviour)]
    key = (tuple(str(p.resolve()) for p in paths), files_key(*(f for p in paths for f in _dataset_files(p))))
    held = _HELD_PAIR.take(key)
    if held is not None:
        return key, held
    names = {"expert": f"Minari expert dataset {data.expert!r}",
             "behaviour": f"Minari behaviour dataset {data.behaviour!r}"}
    expert_ds, behaviour_ds = _open(data.expert, data.data_path), _open(data.behaviour, data.data_path)
    for role, ds in (("expert", expert_ds), ("behaviour", behaviour_ds)):
        _check_spaces(ds.observation_space, ds.action_space, names[role])
        if ds.total_steps == 0:
            raise ValueError(f"{names[role]} holds no steps ({ds.total_episodes} episodes): it is empty; give a "
                             f"dataset with data.")
    for what in ("observation_space", "action_space"):
        a, b = getattr(expert_ds, what), getattr(behaviour_ds, what)
        if a != b:
            raise ValueError(
                f"The Minari datasets have different {what.replace('_', ' ')}s: expert {data.expert!r} has "
                f"{_space_text(a)}, behaviour {data.behaviour!r} has {_space_text(b)}. Both must come from the same env."
            )
    envs = [getattr(getattr(ds.spec, "env_spec", None), "id", None) for ds in (expert_ds, behaviour_ds)]
    if None not in envs and envs[0] != envs[1]:
        raise ValueError(f"The Minari datasets come from different envs: expert {data.expert!r} from {envs[0]!r}, "
                         f"behaviour {data.behaviour!r} from {envs[1]!r}. Both must come from the same env.")
    pair = (expert_ds, behaviour_ds,
            read_dataset_transitions(expert_ds, paths[0], name=names["expert"], cache=data.cache),
            read_dataset_transitions(behaviour_ds, paths[1], name=names["behaviour"], cache=data.cache))
    return key, pair


def _check_expert_episodes(data: MinariDataConfig, expert: TensorDictBase) -> None:
    """Refuse ``env.minari.expert_episodes`` below 1 or above the expert dataset's episode count, in one line."""
    wanted = data.expert_episodes
    if wanted is None:
        return
    held = int(torch.unique(expert[EPISODE]).numel())
    if not 1 <= int(wanted) <= held:
        raise ValueError(f"env.minari.expert_episodes={wanted} but the Minari expert dataset {data.expert!r} holds "
                         f"{held} episode(s) with steps: ask for 1 to {held}, or null for all.")


def draw_expert_episodes(expert: TensorDictBase, count: int | None, *, seed: int) -> TensorDictBase:
    """The rows of ``count`` of ``expert``'s episodes (its ``"episode"`` ids), drawn without replacement by ``seed``
    (a ``torch.Generator`` seeded ``seed + 5``); ``None``: every row. The rows keep their order; the same seed draws
    the same episodes.

        >>> from tensordict import TensorDict
        >>> td = TensorDict({"episode": torch.tensor([0, 0, 1, 1, 2, 2])}, [6])
        >>> draw_expert_episodes(td, 2, seed=0)["episode"].unique().numel()
        2
    """
    if count is None:
        return expert
    ids = torch.unique(expert[EPISODE])
    if not 1 <= int(count) <= ids.numel():
        raise ValueError(f"draw_expert_episodes: count must lie in [1, {ids.numel()}] (the episodes held), got {count}.")
    generator = torch.Generator().manual_seed(int(seed) + 5)
    chosen = ids[torch.randperm(ids.numel(), generator=generator)[: int(count)]]
    return expert[torch.isin(expert[EPISODE], chosen)]


def check_minari_data(data: MinariDataConfig, *, keep: bool = False) -> None:
    """Everything that can refuse the Minari datasets ``data``, read and checked: both are given and on disk, have
    supported and equal observation and action spaces, come from the same env (where both record one), hold steps,
    and every observation, action and reward is finite and every action lies in the action space; the behaviour
    dataset holds enough episodes to split. A refusal is a one-line ``ValueError`` (``FileNotFoundError`` for a
    dataset not on disk) naming the dataset and, for a bad value, the episode, the first offending step and the key.
    Without ``eval_env``, the env recorded in the datasets must be the registered one (:func:`trusted_env_spec`).

    ``keep=True`` holds the data read for the next :func:`make_minari_datasets` on the same, unchanged files (once):
    a run checks its data before it writes anything, and its trainer then reads them once only.
    """
    key, pair = _read_pair(data)
    _check_expert_episodes(data, pair[2])
    behaviour = pair[3]
    episodes = int(torch.unique(behaviour[EPISODE]).numel())
    needed = min_behaviour_episodes(data.ratio_fraction)
    if episodes < needed:
        raise ValueError(
            f"The Minari behaviour dataset {data.behaviour!r} holds {episodes} episode(s) with steps; at least {needed} "
            f"are needed (env.minari.ratio_fraction={data.ratio_fraction}: S^b takes at least one episode and D keeps "
            f"at least two, which the trainer splits into its training and held-out sets)."
        )
    if not data.eval_env:  # the evaluation env is made from the recorded spec: refused now if that would run code
        for ds in pair[:2]:
            spec = _recorded_spec(ds)
            if spec is not None:
                trusted_env_spec(spec, {"expert_dataset": data.expert})
                break
    check_eval_env(data, *pair)
    if keep:
        _HELD_PAIR.hold(key, pair)


def check_eval_env(data: MinariDataConfig, expert_ds, behaviour_ds, expert: TensorDictBase,
                   behaviour: TensorDictBase) -> None:
    """Refuse, before anything is written, an evaluation env whose figures would not compare with the data's: an id
    gymnasium does not know, observations or actions of another shape, action bounds other than the datasets' (a
    policy trained on the data's range would be clipped by the env), or a time limit (``max_episode_steps``) shorter
    than the data's longest episode (its returns would be of shorter episodes than the data's). The env is
    ``env.minari.eval_env``, else the one the datasets record (nothing is checked when neither names one). One line
    naming the env, the setting and what differs."""
    from gymnasium import spaces

    from gymnasium.envs.registration import EnvSpec

    recorded = None if data.eval_env else _recorded_spec_json(expert_ds, behaviour_ds)
    env_id = data.eval_env or _recorded_env_id(expert_ds) or _recorded_env_id(behaviour_ds)
    if not env_id:
        return
    where = (f"env.minari.eval_env={data.eval_env}" if data.eval_env
             else f"the evaluation env {env_id!r} the Minari datasets record")
    try:
        genv = _make_gym_env(EnvSpec.from_json(recorded) if recorded else env_id)
    except Exception as err:  # noqa: BLE001 (gymnasium's Error for an unknown id, a missing simulator, ...)
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ValueError(f"{where}: the env cannot be made ({type(err).__name__}: {first}); pass "
                         f"env.minari.eval_env=<a registered gymnasium id> of the env the data come from.") from None
    try:
        data_obs, data_act = expert_ds.observation_space, expert_ds.action_space
        if tuple(genv.observation_space.shape or ()) != tuple(data_obs.shape or ()):
            raise ValueError(f"{where}: its observations have the shape {genv.observation_space.shape}, the Minari "
                             f"datasets' {data_obs.shape} ({data_obs}); evaluate on the env the data come from.")
        if type(genv.action_space) is not type(data_act) or (
                isinstance(data_act, spaces.Box) and tuple(genv.action_space.shape) != tuple(data_act.shape)):
            raise ValueError(f"{where}: its action space is {genv.action_space}, the Minari datasets' {data_act}; "
                             f"evaluate on the env the data come from.")
        if isinstance(data_act, spaces.Box) and not (
                np.allclose(genv.action_space.low, data_act.low) and np.allclose(genv.action_space.high, data_act.high)):
            raise ValueError(f"{where}: its action bounds {genv.action_space} differ from the Minari datasets' "
                             f"{data_act}: a policy trained on the data's range would be clipped by the env, and its "
                             f"returns would not be the data's policy's. Record the env's own action space in the "
                             f"datasets, or evaluate on an env with the data's bounds.")
        limit = genv.spec.max_episode_steps if genv.spec is not None else None
        longest = max(int(torch.unique(td[EPISODE], return_counts=True)[1].max()) for td in (expert, behaviour))
        if limit is not None and limit < longest:
            raise ValueError(f"{where}: it ends episodes after {limit} steps (max_episode_steps), but the Minari "
                             f"datasets hold episodes of {longest} steps: evaluation returns would be of shorter "
                             f"episodes than the data's. Record the env's real time limit in the datasets, or pass "
                             f"env.minari.eval_env=<id> of an env with it.")
    finally:
        genv.close()


def make_minari_datasets(data: MinariDataConfig, *, seed: int = 0, storage: str = "lazy",
                         scratch_dir=None) -> OfflineDatasets:
    """``S^e`` from ``data.expert`` (``data.expert_episodes`` of its episodes, drawn by ``seed``: all when ``None``);
    ``D`` and ``S^b`` from ``data.behaviour`` split by episode (seeded by ``seed``).

    The datasets are checked as they are read (:func:`check_minari_data`): bad data are refused, never trained on.

    Metadata record both datasets' ids and paths, their mean undiscounted episode returns (complete episodes), the
    spaces, the action bounds and the evaluation env's id (``None`` if neither the config nor the dataset names
    one).
    """
    from gymnasium import spaces

    _, (expert_ds, behaviour_ds, expert, behaviour) = _read_pair(data)
    _check_expert_episodes(data, expert)
    expert_pool_episodes = int(torch.unique(expert[EPISODE]).numel())
    expert = draw_expert_episodes(expert, data.expert_episodes, seed=seed)
    action_space = expert_ds.action_space
    if isinstance(action_space, spaces.Discrete):
        low, high, discrete = [0.0] * int(action_space.n), [1.0] * int(action_space.n), int(action_space.n)
    else:
        low, high = (bound.tolist() for bound in _flat_bounds(action_space))
        discrete = None
    metadata = {
        "env": "minari",
        "expert_dataset": data.expert,
        "behaviour_dataset": data.behaviour,
        "expert_path": str(resolve_minari_dataset(data.expert, data.data_path)),
        "behaviour_path": str(resolve_minari_dataset(data.behaviour, data.data_path)),
        "observation_space": _space_text(expert_ds.observation_space),
        "action_space": _space_text(action_space),
        "action_low": low,
        "action_high": high,
        "discrete_actions": discrete,
        "eval_env": data.eval_env or _recorded_env_id(expert_ds) or _recorded_env_id(behaviour_ds),
        # the recorded spec (entry point, kwargs, wrappers) when the env is the dataset's: gymnasium.make of it needs
        # no registration, so an env registered only where the data were made (a reshaped one) is recovered too
        "eval_env_spec": None if data.eval_env else _recorded_spec_json(expert_ds, behaviour_ds),
        "observation_shape": list(expert_ds.observation_space.shape),
        # a multi-dimensional Box action is read flat (row-major); the evaluation env reshapes the policy's back
        "action_shape": list(action_space.shape) if isinstance(action_space, spaces.Box) else None,
        "max_episode_steps": _recorded_max_steps(expert_ds),
        "seed": seed,
        "behaviour_mean_return": _mean_return(behaviour),
        "expert_mean_return": _mean_return(expert),
        "behaviour_episodes": int(torch.unique(behaviour[EPISODE]).numel()),
        "expert_episodes": int(torch.unique(expert[EPISODE]).numel()),
        # env.minari.expert_episodes: the episodes drawn from the expert dataset's (by the seed), else all of them
        "expert_dataset_episodes": expert_pool_episodes,
        "expert_episode_ids": (None if data.expert_episodes is None
                               else sorted(int(i) for i in torch.unique(expert[EPISODE]))),
        # which of the behaviour dataset's episodes (Minari ids, as D's "episode") are the expert's, where the dataset
        # says (metadata "expert_episode_ids", written by torchrl_wbrm.data.benchmark); None where it does not
        "behaviour_expert_episode_ids": _recorded_expert_episodes(behaviour_ds),
        # Minari's reference scores (random actions, the expert), where the dataset records them: D4RL's normalised
        # score of the evaluated returns
        "ref_min_score": _reference_score(expert_ds, behaviour_ds, "ref_min_score"),
        "ref_max_score": _reference_score(expert_ds, behaviour_ds, "ref_max_score"),
    }
    return OfflineDatasets.from_behaviour_and_expert(
        behaviour,
        expert.select("observation", "action", EPISODE),
        ratio_fraction=data.ratio_fraction,
        generator=torch.Generator().manual_seed(seed + 3),
        metadata=metadata,
        storage=storage,
        scratch_dir=scratch_dir,
    )


def _reference_score(expert_ds, behaviour_ds, key: str) -> float | None:
    """The datasets' ``ref_min_score`` / ``ref_max_score`` (the expert dataset's first), or ``None``."""
    for ds in (expert_ds, behaviour_ds):
        value = ds.storage.metadata.get(key)
        if value is not None:
            return float(value)
    return None


def _recorded_expert_episodes(dataset) -> list[int] | None:
    """The ids of ``dataset``'s episodes that are the expert's, as its metadata records them (``None``: not said)."""
    ids = dataset.storage.metadata.get("expert_episode_ids")
    return None if ids is None else sorted(int(i) for i in ids)


def _mean_return(data: TensorDictBase) -> float | None:
    returns = episode_returns(data)
    return float(returns.mean()) if returns.numel() else None


def _recorded_spec(dataset):
    spec = dataset.spec
    return getattr(spec, "eval_env_spec", None) or getattr(spec, "env_spec", None)


def _recorded_env_id(dataset) -> str | None:
    spec = _recorded_spec(dataset)
    return None if spec is None else spec.id


def _recorded_spec_json(*datasets) -> str | None:
    for dataset in datasets:
        spec = _recorded_spec(dataset)
        if spec is not None:
            return spec.to_json()
    return None


def _recorded_max_steps(dataset) -> int | None:
    spec = _recorded_spec(dataset)
    return None if spec is None else spec.max_episode_steps


#: entry points of this package that a dataset may record (``register_reshaped_env``'s envs): they make a registered
#: gymnasium env by its id and reshape it, nothing else
PACKAGE_ENTRY_POINTS = ("torchrl_wbrm.data.minari_examples:make_reshaped_env",)


def trusted_env_spec(spec, metadata: dict | None = None):
    """``spec`` (a gymnasium ``EnvSpec`` read from a dataset) if making it runs only registered code.

    ``gymnasium.make`` of a spec imports and calls its ``entry_point`` and its ``additional_wrappers``' entry points,
    and a dataset file can name any importable callable there. So a recorded spec is used only when its entry point
    is the one gymnasium has registered for its id in this process (or one of :data:`PACKAGE_ENTRY_POINTS`), and
    each of its wrappers is one of gymnasium's own (``gymnasium.wrappers``); anything else is refused in one line
    naming the dataset and the entry point. An env of your own: register it (import the package that registers it)
    and pass ``env.minari.eval_env=<its id>``, which makes the registered env and ignores the recorded spec.

        >>> from gymnasium.envs.registration import EnvSpec
        >>> trusted_env_spec(EnvSpec("Pendulum-v1", entry_point="gymnasium.envs.classic_control.pendulum:PendulumEnv")).id
        'Pendulum-v1'
        >>> trusted_env_spec(EnvSpec("Pendulum-v1", entry_point="os:system"))
        Traceback (most recent call last):
        ...
        ValueError: The Minari dataset None records the env 'Pendulum-v1' with the entry point 'os:system', not the registered 'gymnasium.envs.classic_control.pendulum:PendulumEnv'; a recorded entry point is not run. Pass env.minari.eval_env=<gymnasium id> to evaluate on a registered env.
    """
    import gymnasium as gym

    name = None if metadata is None else metadata.get("expert_dataset")
    if spec.entry_point not in PACKAGE_ENTRY_POINTS:
        registered = gym.registry.get(spec.id)
        if registered is None:
            raise ValueError(
                f"The Minari dataset {name!r} records the env {spec.id!r}, which gymnasium has not registered in this "
                f"process; its recorded entry point {spec.entry_point!r} is not run. Register the env (import the "
                f"package that registers it) and pass env.minari.eval_env={spec.id}."
            )
        if spec.entry_point != registered.entry_point:
            raise ValueError(
                f"The Minari dataset {name!r} records the env {spec.id!r} with the entry point {spec.entry_point!r}, "
                f"not the registered {registered.entry_point!r}; a recorded entry point is not run. Pass "
                f"env.minari.eval_env=<gymnasium id> to evaluate on a registered env."
            )
    for wrapper in spec.additional_wrappers or ():
        entry = str(getattr(wrapper, "entry_point", ""))
        if not entry.startswith("gymnasium.wrappers"):
            raise ValueError(
                f"The Minari dataset {name!r} records the env {spec.id!r} with the wrapper {entry!r}, which is not one "
                f"of gymnasium's own (gymnasium.wrappers); it is not run. Pass env.minari.eval_env={spec.id} to "
                f"evaluate on the registered env."
            )
    return spec


def make_minari_eval_env(metadata: dict, *, seed: int | None = None, num_envs: int | None = None):
    """The torchrl env of the datasets' gymnasium env (``metadata`` of :func:`make_minari_datasets`).

    With ``num_envs``, ``num_envs`` copies in one gymnasium ``SyncVectorEnv`` (batch ``[num_envs]``, auto-reset on
    the step that ends an episode): a policy acts on the whole batch at once, and ``set_seed(s)`` resets copy ``i``
    with ``s + i``, so its first episodes are those of the single env seeded ``s + i`` one by one.

    The env is ``gymnasium.make`` of the spec recorded in the dataset (as ``MinariDataset.recover_environment``
    does), or of the id ``env.minari.eval_env``, wrapped in torchrl's ``GymWrapper``. Its observation is cast to
    float32 (``DoubleToFloat``, ``DTypeCastTransform``) and, when multi-dimensional, flattened row-major
    (``FlattenObservation``), as :func:`read_minari_transitions` reads the data; a multi-dimensional ``Box`` action
    is taken flat and reshaped row-major before it reaches gym (gymnasium's ``TransformAction``). For a ``Discrete``
    action the env is
    built one-hot (``categorical_action_encoding=False``) and takes the policy's ``n`` scores: the inverse transform
    steps gym with their ``argmax``. Raises a ``ValueError`` when no env is known (datasets that record none, and no
    ``env.minari.eval_env``) or when the env's observation does not match the datasets', and gymnasium's own error
    for an id it does not know.
    """
    import gymnasium as gym
    from gymnasium.envs.registration import EnvSpec
    from torchrl.envs import Compose, DoubleToFloat, DTypeCastTransform, FlattenObservation, GymWrapper, Transform
    from torchrl.envs import TransformedEnv

    class ScoresToOneHot(Transform):
        """The policy writes ``n`` scores; the env gets the one-hot vector of their argmax."""

        def __init__(self):
            super().__init__(in_keys_inv=["action"], out_keys_inv=["action"])

        def _inv_apply_transform(self, action: torch.Tensor) -> torch.Tensor:
            return torch.nn.functional.one_hot(action.argmax(-1), action.shape[-1]).to(torch.long)

    env_id = metadata.get("eval_env")
    if not env_id:
        raise ValueError(
            f"The Minari datasets {metadata.get('expert_dataset')!r} / {metadata.get('behaviour_dataset')!r} record no "
            f"gymnasium env to evaluate on: pass env.minari.eval_env=<gymnasium id>."
        )
    recorded = metadata.get("eval_env_spec")
    spec = trusted_env_spec(EnvSpec.from_json(recorded), metadata) if recorded else env_id
    action_shape = metadata.get("action_shape")

    def make_one():
        genv = _make_gym_env(spec)
        if action_shape is not None:
            if not isinstance(genv.action_space, gym.spaces.Box) or list(genv.action_space.shape) != list(action_shape):
                raise ValueError(f"The evaluation env {env_id!r} has the action space {genv.action_space}, the Minari "
                                 f"datasets' is {metadata.get('action_space')}.")
            if len(action_shape) > 1:  # the policy acts flat, as the data were read: reshape it back (row-major)
                box = genv.action_space
                genv = gym.wrappers.TransformAction(
                    genv, lambda a, shape=tuple(box.shape), dtype=box.dtype: np.asarray(a, dtype=dtype).reshape(shape),
                    gym.spaces.Box(box.low.reshape(-1), box.high.reshape(-1), dtype=box.dtype))
        return genv

    if num_envs is None:
        genv = make_one()
    else:
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"make_minari_eval_env: num_envs must be a positive integer, got {num_envs!r}.")
        make_one().close()  # the checks above, once, before the copies are built
        genv = gym.vector.SyncVectorEnv([make_one] * num_envs, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
    base = GymWrapper(genv, categorical_action_encoding=False, device="cpu")
    transforms = []
    if metadata.get("discrete_actions"):
        transforms.append(ScoresToOneHot())
    if any(spec.dtype == torch.float64 for spec in base.observation_spec.values(True, True)):
        transforms.append(DoubleToFloat())
    observation = base.observation_spec.get("observation", None)
    if observation is None:
        raise ValueError(f"The evaluation env {env_id!r} has no 'observation' entry (its observation spec: "
                         f"{base.observation_spec}); a Box observation is needed.")
    if observation.dtype not in (torch.float32, torch.float64):
        transforms.append(DTypeCastTransform(observation.dtype, torch.float32, in_keys=["observation"]))
    shape = list(observation.shape)[len(base.batch_size):]  # without the vector env's batch
    expected = metadata.get("observation_shape")
    if expected is not None and shape != list(expected):
        raise ValueError(f"The evaluation env {env_id!r} has observations of shape {tuple(shape)}, the Minari "
                         f"datasets' of shape {tuple(expected)} (observation space "
                         f"{metadata.get('observation_space')}).")
    if len(shape) > 1:
        transforms.append(FlattenObservation(-len(shape), -1, in_keys=["observation"]))
    if isinstance(base, TransformedEnv):  # a vector env comes with torchrl's own auto-reset transform: extend it
        for transform in transforms:
            base.append_transform(transform)
        env = base
    else:
        env = TransformedEnv(base, Compose(*transforms)) if transforms else base
    if seed is not None:
        env.set_seed(seed)
    return env


class OneHotActions(torch.nn.Module):
    """The ``n`` actions of a ``Discrete(n)`` space as ``algo=dqn``'s action grid (the interface of
    :class:`~torchrl_wbrm.modules.ActionGrid`): ``index(one_hot) -> argmax``, ``forward(index) -> one-hot``.
    ``num_bins`` does not apply: the actions are already discrete."""

    def __init__(self, num_actions: int) -> None:
        super().__init__()
        self.register_buffer("values", torch.eye(int(num_actions)))

    @property
    def num_actions(self) -> int:
        return int(self.values.shape[0])

    def index(self, action: torch.Tensor) -> torch.Tensor:
        return action.argmax(-1)

    def forward(self, index: torch.Tensor) -> torch.Tensor:
        return self.values[index]  # categorical indices [*B] -> one-hot [*B, n] (a batch of one stays one)


@contextlib.contextmanager
def _minari_path(root: Path):
    previous = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(root)
    try:
        yield
    finally:
        if previous is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = previous


def write_minari_dataset(
    dataset_id: str,
    episodes: Iterable[dict],
    *,
    data_path: str | os.PathLike | None = None,
    env: str | None = None,
    eval_env: str | None = None,
    observation_space=None,
    action_space=None,
    algorithm_name: str | None = None,
    description: str | None = None,
    author: str | None = None,
    ref_min_score: float | None = None,
    ref_max_score: float | None = None,
    num_episodes_average_score: int = 100,
    metadata: dict | None = None,
):
    """Write ``episodes`` as the Minari dataset ``dataset_id`` under ``data_path`` (default: Minari's data path).

    Each episode is a dict of arrays: ``observations`` (``T + 1`` rows), ``actions``, ``rewards``, ``terminations``
    and ``truncations`` (``T`` rows). Written with ``minari.create_dataset_from_buffers`` from ``EpisodeBuffer``
    objects (``minari[hdf5]`` only; no jax). ``env`` (a registered gymnasium id) records the env and its spaces; an
    env that gymnasium does not know (the LQR systems) needs ``observation_space`` and ``action_space`` instead.
    ``ref_min_score`` / ``ref_max_score`` (both or neither) are the returns of random actions and of the expert,
    Minari's reference scores for D4RL's normalised score (averaged over ``num_episodes_average_score`` episodes).
    ``metadata``: more keys for the dataset's ``metadata.json`` (``MinariStorage.update_metadata``), e.g.
    ``"expert_episode_ids"``, the ids of the episodes that are the expert's (:func:`make_minari_datasets` reads it).
    Returns the ``MinariDataset``.
    """
    import minari
    from minari.data_collector.episode_buffer import EpisodeBuffer

    buffers = []
    for i, ep in enumerate(episodes):
        buffers.append(EpisodeBuffer(
            id=i,
            observations=np.asarray(ep["observations"]),
            actions=np.asarray(ep["actions"]),
            rewards=[float(r) for r in np.asarray(ep["rewards"]).reshape(-1)],
            terminations=[bool(t) for t in np.asarray(ep["terminations"]).reshape(-1)],
            truncations=[bool(t) for t in np.asarray(ep["truncations"]).reshape(-1)],
            infos={},
        ))
    root = minari_data_root(data_path)
    root.mkdir(parents=True, exist_ok=True)
    with _minari_path(root), warnings.catch_warnings():  # Minari's advice on optional metadata (author e-mail, ...)
        warnings.filterwarnings("ignore", message=r".* is set to None", category=UserWarning)
        warnings.filterwarnings("ignore", message=r"env_spec is None", category=UserWarning)
        dataset = minari.create_dataset_from_buffers(
            dataset_id=dataset_id, buffer=buffers, env=env, eval_env=eval_env, algorithm_name=algorithm_name,
            observation_space=observation_space, action_space=action_space, description=description, author=author,
            ref_min_score=ref_min_score, ref_max_score=ref_max_score,
            num_episodes_average_score=num_episodes_average_score,
        )
        if metadata:
            dataset.storage.update_metadata(dict(metadata))
        return dataset


def transitions_to_episodes(data: TensorDictBase) -> list[dict]:
    """Flat transitions (``"episode"`` ids; the steps of an episode in time order, though not necessarily
    contiguous, as a collector writes them) -> the episode dicts of :func:`write_minari_dataset`, in order of
    episode id (``observations`` gets the episode's last ``("next", "observation")`` appended)."""
    ids = data[EPISODE]
    order = torch.argsort(ids, stable=True)  # stable: each episode's steps keep their time order
    data, ids = data[order], ids[order]
    _, counts = torch.unique_consecutive(ids, return_counts=True)
    episodes, start = [], 0
    for count in counts.tolist():
        ep = data[start:start + count]
        start += count
        obs = torch.cat([ep["observation"], ep["next", "observation"][-1:]], 0)
        episodes.append({
            "observations": obs.numpy(),
            "actions": ep["action"].numpy(),
            "rewards": ep["next", "reward"].reshape(-1).numpy(),
            "terminations": ep["next", "terminated"].reshape(-1).numpy(),
            "truncations": ep["next", "truncated"].reshape(-1).numpy(),
        })
    return episodes
