"""One entry point from an environment config to its offline datasets (used by every recipe)."""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

from torchrl_wbrm.data.datasets import OfflineDatasets
from torchrl_wbrm.data.lqr import LQRDataConfig
from torchrl_wbrm.data.minari_data import MinariDataConfig
from torchrl_wbrm.data.mountain_car import MountainCarDataConfig
from torchrl_wbrm.tasks.base import to_dataclass
from torchrl_wbrm.tasks.registry import TASKS, get_task
from torchrl_wbrm.envs import LQRConfig

__all__ = ["EnvConfig", "ENV_KINDS", "make_offline_datasets", "cached_offline_datasets"]

#: the env kinds, one per registered task (:data:`torchrl_wbrm.tasks.TASKS`)
ENV_KINDS = tuple(TASKS)


@dataclass
class EnvConfig:
    """Which environment, with which data (a Hydra structured config; see ``configs/env/``).

    Attributes:
        name: a label for logs and tables (``lqr_exp1``, ``mountain_car``, ...).
        kind: the task (:data:`~torchrl_wbrm.tasks.TASKS`): ``"lqr"``, ``"mountain_car"`` or ``"minari"`` (two
            local Minari datasets, ``minari``).
        lqr: the LQR system (any F, G, R; the paper's three are ``configs/env/lqr_exp{1,2,3}.yaml``).
        lqr_data: LQR dataset sizes and policies.
        mountain_car_data: MountainCar dataset sizes and policies.
        minari: the expert and behaviour Minari datasets and the evaluation env (``kind="minari"``).
    """

    name: str = "lqr_exp1"
    kind: str = "lqr"
    lqr: LQRConfig = field(default_factory=LQRConfig)
    lqr_data: LQRDataConfig = field(default_factory=LQRDataConfig)
    mountain_car_data: MountainCarDataConfig = field(default_factory=MountainCarDataConfig)
    minari: MinariDataConfig = field(default_factory=MinariDataConfig)

    def __post_init__(self):
        if self.kind not in TASKS:
            raise ValueError(f"env.kind must be one of {tuple(TASKS)}, got {self.kind!r}.")


def make_offline_datasets(env: EnvConfig, *, seed: int, storage: str = "lazy", scratch_dir=None) -> OfflineDatasets:
    """Collect (or read) the three sets (``D``, ``S^b``, ``S^e``) for ``env`` with ``seed``: its task's
    :meth:`~torchrl_wbrm.tasks.Task.make_datasets`."""
    return get_task(to_dataclass(EnvConfig, env)).make_datasets(seed=seed, storage=storage, scratch_dir=scratch_dir)


def saved_dataset_dir(task) -> str | None:
    """The saved dataset a task's data config points to (``dataset_dir``, e.g. ``env.lqr_data.dataset_dir``), or
    ``None`` when its data are collected."""
    return getattr(getattr(task, "data_config", None), "dataset_dir", None) or None


def _check_cache_entry(target: Path, request: dict, expected: dict[str, int]) -> OfflineDatasets:
    """Load a cache entry (every file verified by :meth:`OfflineDatasets.load`) and check that its metadata match
    the request (the whole env config and the seed) and its sizes the config's; raises ``ValueError`` naming what
    differs."""
    meta = OfflineDatasets.read_metadata(target)
    if meta.get("cache_request") != request:
        raise ValueError(
            f"{target}: its metadata record the request {meta.get('cache_request')!r}, not {request!r}."
        )
    datasets = OfflineDatasets.load(target)
    sizes = datasets.sizes()
    found = {"behaviour": sizes["transitions"] + sizes["behaviour_samples"], "expert_samples": sizes["expert_samples"]}
    if found != expected:
        raise ValueError(f"{target}: it holds {found} samples, the env config asks for {expected}.")
    return datasets


def cached_offline_datasets(env: EnvConfig, *, seed: int, cache_dir: str | os.PathLike) -> OfflineDatasets:
    """:func:`make_offline_datasets`, saved under ``cache_dir`` and loaded on later calls with the same env and seed.

    Data already on disk are not cached: a Minari pair, or a dataset saved with :meth:`OfflineDatasets.save` and named by
    the env config (``env.lqr_data.dataset_dir``), is read and verified where it is, so a regenerated dataset is always
    the one trained on. The key is a hash of the whole env config and the seed, so any change of data settings makes
    new data. Before
    an entry is used, every file is verified against the checksums, sizes, dtypes and shapes in its
    ``metadata.json`` (:meth:`OfflineDatasets.load`), and its recorded request (env config and seed) and sizes are
    compared with this call's. A bad entry is never patched: it is rebuilt in a private folder, swapped into place
    by renames, and a one-line warning says so. Runs in parallel may race to write one entry: each writes a
    private folder and renames it into place; a loser loads the winner's copy (same config, same seed).
    """
    env = to_dataclass(EnvConfig, env)
    task = get_task(env)
    expected = task.expected_sizes()
    if expected is None or saved_dataset_dir(task) is not None:
        # already on disk (Minari, or a saved dataset such as env.lqr_data.dataset_dir), verified by its reader
        # against its own checksums on every load: no second copy, which would go stale when the data are remade
        return task.make_datasets(seed=seed)
    request = json.loads(json.dumps({"env": asdict(env), "seed": seed}, sort_keys=True, default=str))
    key = hashlib.sha1(json.dumps(request, sort_keys=True).encode()).hexdigest()
    target = Path(cache_dir) / f"{env.name}_seed{seed}_{key[:12]}"
    if target.is_dir():
        try:
            return _check_cache_entry(target, request, expected)
        except (OSError, ValueError, KeyError) as err:
            warnings.warn(f"Data cache entry {target} failed verification and is rebuilt: {err}", stacklevel=2)
            reason = err
    else:
        reason = None
    datasets = task.make_datasets(seed=seed)
    datasets.metadata["cache_request"] = request
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=target.parent, prefix=".tmp_"))
    datasets.save(tmp)
    if reason is not None and target.is_dir():  # move the bad entry aside (one rename), then put the new one in
        bad = Path(tempfile.mkdtemp(dir=target.parent, prefix=".bad_"))
        try:
            os.rename(target, bad / target.name)
        except OSError:  # another run moved it first
            pass
        shutil.rmtree(bad, ignore_errors=True)
    try:
        os.rename(tmp, target)
    except OSError:  # another run got there first: use its copy, verified
        shutil.rmtree(tmp, ignore_errors=True)
        return _check_cache_entry(target, request, expected)
    return datasets
