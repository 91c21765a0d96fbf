"""torchrl_wbrm.data.datasets: saved datasets' integrity, and the data cache.

Every failure case asserts the error type and that the message names the file, key or shape; the load tests also
check that nothing on disk changed.
"""
from __future__ import annotations

import hashlib
import json
import os
import warnings
from pathlib import Path

import pytest
import torch

from torchrl_wbrm.data import LQRDataConfig, OfflineDatasets, make_lqr_datasets
from torchrl_wbrm.tasks import EnvConfig, cached_offline_datasets

SMALL = LQRDataConfig(behaviour_episodes=40, expert_episodes=20, parallel_envs=20)


def snapshot(root: Path) -> dict[str, tuple[int, str, float]]:
    """Every file under ``root``: (size, SHA-256, mtime)."""
    out = {}
    for path in sorted(Path(root).rglob("*")):
        if path.is_file():
            out[str(path.relative_to(root))] = (
                path.stat().st_size, hashlib.sha256(path.read_bytes()).hexdigest(), path.stat().st_mtime_ns
            )
    return out


@pytest.fixture(scope="module")
def small_data():
    return make_lqr_datasets("exp1", SMALL, seed=0)


@pytest.fixture
def saved(tmp_path, small_data):
    return small_data.save(tmp_path / "ds")


def test_metadata_records_every_file(saved, small_data):
    meta = json.loads((saved / "metadata.json").read_text())
    assert meta["format_version"] == 2
    obs = meta["files"]["transitions"]["observation"]
    assert obs["file"] == "transitions/observation.memmap" and obs["dtype"] == "torch.float32"
    assert obs["shape"] == [small_data.sizes()["transitions"], 2]
    assert obs["bytes"] == (saved / obs["file"]).stat().st_size == obs["shape"][0] * 2 * 4
    assert obs["sha256"] == hashlib.sha256((saved / obs["file"]).read_bytes()).hexdigest()
    assert meta["files"]["transitions"]["next/terminated"]["dtype"] == "torch.bool"
    for part in ("transitions", "behaviour_samples", "expert_samples"):
        for entry in meta["files"][part].values():
            assert (saved / entry["file"]).is_file()
    loaded = OfflineDatasets.load(saved)
    assert (loaded.transitions[:]["next", "reward"] == small_data.transitions[:]["next", "reward"]).all()
    assert loaded.transitions[:]["next", "terminated"].dtype == torch.bool


@pytest.mark.parametrize(
    "rel, size, found",
    [("transitions/observation.memmap", 0, "has 0 bytes"), ("transitions/next/reward.memmap", 1000, "has 1000 bytes")],
)
def test_truncated_file_is_refused_and_left_alone(saved, rel, size, found):
    file = saved / rel
    expected = file.stat().st_size
    os.truncate(file, size)
    before = snapshot(saved)
    with pytest.raises(ValueError, match=rf"{rel}.*{found}, expected {expected}"):
        OfflineDatasets.load(saved)
    assert snapshot(saved) == before  # never padded, never rewritten
    assert file.stat().st_size == size


def test_same_size_garbage_is_refused_by_its_checksum(saved):
    file = saved / "expert_samples" / "action.memmap"
    size = file.stat().st_size
    file.write_bytes(b"\xff" * size)  # NaN patterns in float32
    before = snapshot(saved)
    with pytest.raises(ValueError, match=r"expert_samples/action.memmap has SHA-256 [0-9a-f]{64}, expected [0-9a-f]{64}"):
        OfflineDatasets.load(saved)
    assert snapshot(saved) == before


def test_missing_file_and_bad_metadata_name_the_file(saved):
    meta_file = saved / "metadata.json"
    meta = json.loads(meta_file.read_text())
    (saved / "behaviour_samples" / "observation.memmap").unlink()
    with pytest.raises(FileNotFoundError, match="behaviour_samples/observation.memmap is missing"):
        OfflineDatasets.load(saved)
    meta["files"]["transitions"]["action"]["shape"] = [7, 2]
    meta_file.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="transitions/action.memmap has 7 rows"):
        OfflineDatasets.load(saved)
    del meta["files"]
    meta_file.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="lists no 'files'"):
        OfflineDatasets.load(saved)
    meta["format_version"] = 1
    meta_file.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="format_version 1, this code reads 2"):
        OfflineDatasets.load(saved)


def test_non_finite_data_are_refused(small_data):
    d = small_data.transitions[:].clone()
    d["next", "reward"][3] = float("nan")
    with pytest.raises(ValueError, match=r"^The transitions set: episode \d+, step \d+ \(row 3\): 'next/reward' is nan;"):
        OfflineDatasets.from_tensordicts(d, small_data.behaviour_samples[:], small_data.expert_samples[:])


def _entry(cache: Path) -> Path:
    (entry,) = [p for p in cache.iterdir() if not p.name.startswith(".")]
    return entry


def test_cache_entry_is_verified_and_rebuilt_atomically(tmp_path):
    env = EnvConfig(lqr_data=SMALL)
    cache = tmp_path / "cache"
    fresh = cached_offline_datasets(env, seed=0, cache_dir=cache)
    entry = _entry(cache)
    good = snapshot(entry)
    # a clean entry is used as it is: no warning, nothing rewritten
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        again = cached_offline_datasets(env, seed=0, cache_dir=cache)
    assert snapshot(entry) == good
    assert (again.transitions[:]["observation"] == fresh.transitions[:]["observation"]).all()
    # truncate two files, as a crashed copy would
    os.truncate(entry / "transitions" / "observation.memmap", 0)
    os.truncate(entry / "transitions" / "next" / "reward.memmap", 1000)
    with pytest.warns(UserWarning, match=r"failed verification and is rebuilt: .*transitions/observation.memmap has 0 bytes") as rec:
        rebuilt = cached_offline_datasets(env, seed=0, cache_dir=cache)
    assert len(rec) == 1 and "\n" not in str(rec[0].message)
    assert (rebuilt.transitions[:]["observation"] == fresh.transitions[:]["observation"]).all()
    assert (rebuilt.transitions[:]["next", "reward"] == fresh.transitions[:]["next", "reward"]).all()
    assert {k: v[:2] for k, v in snapshot(_entry(cache)).items()} == {k: v[:2] for k, v in good.items()}
    assert not [p for p in cache.iterdir() if p.name.startswith(".")]  # no temporary folders left


def test_cache_entry_for_another_request_is_rebuilt(tmp_path):
    env = EnvConfig(lqr_data=SMALL)
    cache = tmp_path / "cache"
    fresh = cached_offline_datasets(env, seed=0, cache_dir=cache)
    entry = _entry(cache)
    meta = json.loads((entry / "metadata.json").read_text())
    meta["cache_request"]["seed"] = 5  # e.g. a folder copied in from another run
    (entry / "metadata.json").write_text(json.dumps(meta))
    with pytest.warns(UserWarning, match=r"failed verification .*request"):
        rebuilt = cached_offline_datasets(env, seed=0, cache_dir=cache)
    assert (rebuilt.expert_samples[:]["action"] == fresh.expert_samples[:]["action"]).all()
    assert json.loads((_entry(cache) / "metadata.json").read_text())["cache_request"]["seed"] == 0
