"""``env.minari.cache``: a Minari dataset's transitions, once read and checked, kept in its ``data/`` folder and
read from there while the dataset's files are unchanged; a stale, damaged, foreign or tampered cache is never
trusted, and a folder that cannot be written is read uncached."""
from __future__ import annotations

import os
import pickle
import shutil

import pytest
import torch

from minari_helpers import mountain_car_datasets
from torchrl_wbrm.data import minari_data
from torchrl_wbrm.data.minari_data import (TRANSITIONS_CACHE, MinariDataConfig, make_minari_datasets,
                                           read_dataset_transitions, read_minari_transitions,
                                           resolve_minari_dataset)
from minari.dataset.minari_dataset import MinariDataset


@pytest.fixture()
def behaviour(tmp_path):
    """A private copy of the MountainCar behaviour dataset's ``data/`` folder (the shared one stays untouched)."""
    data = mountain_car_datasets()
    source = resolve_minari_dataset(data["behaviour"], data["data_path"])
    folder = tmp_path / "behaviour" / "data"
    shutil.copytree(source, folder, ignore=shutil.ignore_patterns(TRANSITIONS_CACHE + "*"))
    return folder


def _reads(monkeypatch) -> list:
    """Count the reads of the dataset's episodes."""
    calls = []
    original = minari_data.read_minari_transitions
    monkeypatch.setattr(minari_data, "read_minari_transitions",
                        lambda *a, **k: calls.append(1) or original(*a, **k))
    return calls


def test_second_read_comes_from_the_cache_and_equals_the_dataset(behaviour, monkeypatch):
    reads = _reads(monkeypatch)
    ds = MinariDataset(str(behaviour))
    first = read_dataset_transitions(ds, behaviour)
    assert (behaviour / TRANSITIONS_CACHE).is_file() and len(reads) == 1
    second = read_dataset_transitions(ds, behaviour)
    assert len(reads) == 1  # read from the cache
    assert (second == read_minari_transitions(ds)).all() and (second == first).all()
    second["observation"].add_(1.0)  # the caller's copy, not the mapped file
    assert (read_dataset_transitions(ds, behaviour) == first).all()
    assert not list(behaviour.glob("*.tmp"))


def test_a_changed_dataset_is_read_again(behaviour, monkeypatch):
    reads = _reads(monkeypatch)
    ds = MinariDataset(str(behaviour))
    read_dataset_transitions(ds, behaviour)
    hdf5 = next(behaviour.glob("main_data.*"))
    stat = hdf5.stat()
    os.utime(hdf5, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))  # the file rewritten (a new time)
    read_dataset_transitions(ds, behaviour)
    assert len(reads) == 2
    read_dataset_transitions(ds, behaviour)  # and cached again for that version
    assert len(reads) == 2


@pytest.mark.parametrize("damage", ["nan", "action", "observation", "shape", "truncated", "pickle"])
def test_a_tampered_or_foreign_cache_is_never_trusted(behaviour, monkeypatch, damage, tmp_path):
    ds = MinariDataset(str(behaviour))
    truth = read_dataset_transitions(ds, behaviour)
    path = behaviour / TRANSITIONS_CACHE
    saved = torch.load(path, weights_only=True)
    if damage == "nan":
        saved["transitions"]["next"]["reward"][3, 0] = float("nan")
    elif damage == "action":
        saved["transitions"]["action"][5, 0] = 7.0  # outside the Box [-1, 1]
    elif damage == "observation":
        saved["transitions"]["observation"][2, 0] = 100.0  # far outside MountainCar's position box [-1.2, 0.6]
    elif damage == "shape":
        saved["transitions"]["observation"] = saved["transitions"]["observation"][:, :1].clone()
    if damage in ("nan", "action", "observation", "shape"):
        torch.save(saved, path)
    elif damage == "truncated":
        path.write_bytes(path.read_bytes()[:100])
    else:  # a pickle that would run code if loaded without weights_only
        marker = tmp_path / "ran"

        class Payload:
            def __reduce__(self):
                return (open, (str(marker), "w"))

        path.write_bytes(pickle.dumps(Payload()))
    reads = _reads(monkeypatch)
    again = read_dataset_transitions(ds, behaviour)
    assert len(reads) == 1 and (again == truth).all()
    assert damage != "pickle" or not (tmp_path / "ran").exists()
    assert (read_dataset_transitions(ds, behaviour) == truth).all() and len(reads) == 1  # the cache was rewritten


def test_cache_off_and_an_unwritable_folder_write_nothing(behaviour, monkeypatch):
    ds = MinariDataset(str(behaviour))
    read_dataset_transitions(ds, behaviour, cache=False)
    assert not (behaviour / TRANSITIONS_CACHE).exists()

    def refuse(path, write, **kw):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(minari_data, "atomic_write", refuse)  # a read-only folder (root writes into chmod 555 ones)
    td = read_dataset_transitions(ds, behaviour)
    assert td.shape[0] == ds.total_steps and not (behaviour / TRANSITIONS_CACHE).exists()


def test_runs_read_the_same_data_with_and_without_the_cache(behaviour, monkeypatch):
    data = mountain_car_datasets()
    expert = behaviour.parent.parent / "expert" / "data"
    shutil.copytree(resolve_minari_dataset(data["expert"], data["data_path"]), expert,
                    ignore=shutil.ignore_patterns(TRANSITIONS_CACHE + "*"))
    config = dict(expert=str(expert), behaviour=str(behaviour))
    cold = make_minari_datasets(MinariDataConfig(**config, cache=False), seed=1)
    reads = _reads(monkeypatch)
    make_minari_datasets(MinariDataConfig(**config), seed=1)
    warm = make_minari_datasets(MinariDataConfig(**config), seed=1)
    assert len(reads) == 2  # each dataset once, then from its cache
    for name in ("transitions", "behaviour_samples", "expert_samples"):
        assert (getattr(warm, name)[:] == getattr(cold, name)[:]).all()
