"""A run's ``data_seconds`` and ``wall_seconds`` count the read of the data on disk that the recipe's checks make
before the run starts (the data they read are held for the run, which then does not read them again)."""
from __future__ import annotations

import pytest

from tests.minari_helpers import MINARI_RUN, mountain_car_datasets

pytestmark = pytest.mark.usefixtures("single_thread")


def compose(*overrides: str):
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from torchrl_wbrm.configs import CONFIG_DIR
    from torchrl_wbrm.training.config import register_configs

    register_configs()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return hydra_compose("wbrm_offline", overrides=list(overrides), return_hydra_config=True)


def test_the_checks_read_is_counted_in_the_runs_data_time(tmp_path):
    from torchrl_wbrm.training import WBRMTrainer
    from torchrl_wbrm.training.hydra_guard import RunDirGuard

    data = mountain_car_datasets()
    run_dir = tmp_path / "run"
    config = compose("env=minari", f"env.minari.data_path={data['data_path']}", f"env.minari.expert={data['expert']}",
                     f"env.minari.behaviour={data['behaviour']}", *MINARI_RUN, "logger=none", "plots=false",
                     f"hydra.run.dir={run_dir}")
    prepared, claim = RunDirGuard.checked(config)
    claim.release()
    read = prepared.task.check_seconds
    assert read > 0  # the checks read the Minari datasets
    trainer = WBRMTrainer(prepared, run_dir, logger=None, progress=False)
    try:
        assert trainer.data_seconds >= read
    finally:
        trainer.release()
