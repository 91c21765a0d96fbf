"""Training on a memory-mapped dataset: env.lqr_data.storage=memmap and env.lqr_data.dataset_dir."""
from __future__ import annotations

import pytest
from torchrl.data import LazyMemmapStorage

from torchrl_wbrm.tasks import make_offline_datasets
from torchrl_wbrm.data.lqr import LQRDataConfig
from torchrl_wbrm.training import WBRMTrainer


def _tiny(**lqr_data):
    from tests.test_training import tiny_config

    return tiny_config(env={"lqr_data": lqr_data})


def test_memmap_storage_trains_like_the_in_memory_one(tmp_path, single_thread):
    memmap = WBRMTrainer(_tiny(storage="memmap"), tmp_path / "memmap", progress=False)
    assert isinstance(memmap.datasets.transitions._storage, LazyMemmapStorage)
    a = memmap.run()  # (each trainer seeds torch's generator when built: build and run one at a time)
    b = WBRMTrainer(_tiny(), tmp_path / "lazy", progress=False).run()
    assert a["final"]["q_error_expert"] == b["final"]["q_error_expert"]  # the same data, the same run


def test_a_saved_dataset_directory_is_trained_on(tmp_path, single_thread):
    cfg = _tiny()
    saved = make_offline_datasets(cfg.env, seed=5)  # another seed than the run's: the run must read these
    saved.save(tmp_path / "data")
    trainer = WBRMTrainer(_tiny(dataset_dir=str(tmp_path / "data"), storage="memmap"), tmp_path / "run",
                          progress=False)
    assert trainer.datasets.sizes() == saved.sizes()
    assert (trainer.datasets.transitions[:]["observation"] == saved.transitions[:]["observation"]).all()
    assert isinstance(trainer.datasets.transitions._storage, LazyMemmapStorage)
    assert trainer.run()["final"]


def test_unknown_storage_is_refused(tmp_path):
    with pytest.raises(ValueError, match="storage must be 'lazy' or 'memmap'"):
        WBRMTrainer(_tiny(storage="disk"), tmp_path / "run", progress=False)


def test_lqr_data_config_defaults_keep_collecting_in_memory():
    assert LQRDataConfig().storage == "lazy" and LQRDataConfig().dataset_dir is None
