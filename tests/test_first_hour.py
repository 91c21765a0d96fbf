"""A new user's first hour: the README's commands as a user types them, and what they print and draw.

- DQN evaluates on a single episode (a batch of one), so ``paper_tables --quick`` runs every registered algorithm
  (that run: tests/test_studies_quick.py);
- the two Minari dataset writers never collide, and an existing id or dataset is refused before any collecting;
- the resume command a run prints works exactly as printed;
- the console: no library [INFO] lines or foreign warnings by default, a config error is one line;
- the figures: each panel its own scale and y-label.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import torch

from tests.references import ROOT

#: a tiny LQR exp1 run of the recipe (seconds)
TINY = [
    "env.lqr_data.behaviour_episodes=40", "env.lqr_data.expert_episodes=20", "env.lqr_data.parallel_envs=20",
    "ratio.steps=10", "ratio.eval_every=5", "ratio.num_cells=[8,8]", "q.steps=10", "q.eval_every=5",
    "q.num_cells=[8,8]", "q.actor_num_cells=[8,8]", "eval.episodes=10", "eval.train_episodes=10",
    "eval.q_samples=100",
]


def run(args: list[str], *, cwd=ROOT, timeout: int = 300, env: dict | None = None) -> subprocess.CompletedProcess:
    """``python <args>`` as a user would run it (captured, with the console's own settings)."""
    full_env = {**os.environ, "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1", "WANDB_MODE": "offline",
                "COLUMNS": "120", **(env or {})}
    return subprocess.run([sys.executable, *args], cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          env=full_env)


def recipe(*overrides: str, script: str = "wbrm_offline.py", **kwargs) -> subprocess.CompletedProcess:
    return run([str(ROOT / "recipes" / script), *overrides], **kwargs)


# ---------------------------------------------------------------------- DQN: a batch of one
def test_the_action_grid_keeps_a_batch_of_one():
    """``algo=dqn eval.train_episodes=1``: the evaluation env has batch [1] and the greedy index shape [1]; the grid
    must return one action of the box's width, [1, m], not drop the batch dimension."""
    from torchrl_wbrm.data.minari_data import OneHotActions
    from torchrl_wbrm.modules import ActionGrid

    grid = ActionGrid.from_lqr_env("exp1", 5)
    for batch in ([1], [3], [1, 1], [2, 1], []):
        index = torch.zeros(batch, dtype=torch.long)
        action = grid(index)
        assert action.shape == (*batch, 2), (batch, action.shape)
        torch.testing.assert_close(grid.index(action), index)
    one_hot = OneHotActions(3)
    assert one_hot(torch.tensor([2])).shape == (1, 3) and one_hot(torch.tensor([[2]])).shape == (1, 1, 3)
    assert one_hot(torch.tensor([2])).tolist() == [[0.0, 0.0, 1.0]]


def test_dqn_evaluates_on_a_single_episode(tmp_path):
    """The reproduction from the report: ``algo=dqn eval.train_episodes=1`` (and ``eval.episodes=1``)."""
    proc = recipe("algo=dqn", *TINY, "eval.train_episodes=1", "eval.episodes=1", "logger=none", "plots=false",
                  f"hydra.run.dir={tmp_path}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["status"] == "finished" and results["algo"] == "dqn" and results["config"]["eval"]["episodes"] == 1
    assert isinstance(results["final"]["regret"], float) and results["final"]["regret"] == results["final"]["regret"]


# ---------------------------------------------------------------------- the dataset writers
TINY_LQR_DATA = ["env.lqr_data.behaviour_episodes=20", "env.lqr_data.expert_episodes=10"]


def _make_dataset_cfg(*dotlist: str):
    from omegaconf import OmegaConf

    from torchrl_wbrm.training.config import MakeDatasetConfig

    return OmegaConf.merge(OmegaConf.structured(MakeDatasetConfig), OmegaConf.from_dotlist(["format=minari", *dotlist]))


def test_make_dataset_and_the_examples_never_share_an_id(tmp_path):
    """Both writers into one Minari data path, for the same env: four ids, each saying what made it."""
    from torchrl_wbrm.data.minari_examples import make_mountain_car_datasets

    proc = recipe("env=mountain_car", "format=minari", f"out={tmp_path}", "env.mountain_car_data.expert_transitions=300",
                  "env.mountain_car_data.behaviour_transitions=600", script="make_dataset.py")
    assert proc.returncode == 0, proc.stderr[-3000:]
    examples = make_mountain_car_datasets(tmp_path, expert_episodes=1, random_episodes=1, noisy_expert_episodes=1)
    assert examples["expert"] == "examples/mountain_car/expert-v0"
    ids = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*-v0"))
    assert ids == ["examples/mountain_car/behaviour-v0", "examples/mountain_car/expert-v0",
                   "make_dataset/mountain_car_seed0/behaviour-v0", "make_dataset/mountain_car_seed0/expert-v0"], ids
    assert "Minari dataset make_dataset/mountain_car_seed0/expert-v0" in proc.stdout


def test_an_existing_minari_id_is_refused_before_any_collecting(tmp_path, monkeypatch):
    from torchrl_wbrm import cli
    from torchrl_wbrm.data import minari_examples
    from torchrl_wbrm.data.minari_data import write_minari_dataset

    episode = {"observations": [[0.0, 0.0], [0.1, 0.0]], "actions": [[0.5]], "rewards": [1.0],
               "terminations": [True], "truncations": [False]}
    for dataset_id in ("make_dataset/lqr_exp1_seed0/expert-v0", "examples/mountain_car/behaviour-v0"):
        write_minari_dataset(dataset_id, [episode], data_path=tmp_path, env="MountainCarContinuous-v0")

    def no_collecting(*args, **kwargs):
        raise AssertionError("collected data before refusing")

    monkeypatch.setattr(cli, "get_task", no_collecting)
    monkeypatch.setattr(minari_examples, "collect_gym_episodes", no_collecting)
    with pytest.raises(FileExistsError) as err:
        cli._write_minari(_make_dataset_cfg("env.name=lqr_exp1"), tmp_path)
    assert "'make_dataset/lqr_exp1_seed0/expert-v0' already exists" in str(err.value)
    assert "minari_namespace=" in str(err.value) and "overwrite=true" in str(err.value)
    with pytest.raises(FileExistsError) as err:
        minari_examples.make_mountain_car_datasets(tmp_path)
    assert "'examples/mountain_car/behaviour-v0' already exists" in str(err.value) and "--namespace" in str(err.value)
    with pytest.raises(ValueError, match=r"'bad name!/expert-v0' is not a Minari dataset id.*minari_namespace="):
        cli._write_minari(_make_dataset_cfg("env.name=lqr_exp1", "minari_namespace=bad name!"), tmp_path)


def make_dataset_here(monkeypatch, capsys, *overrides: str) -> tuple[int, str, str]:
    """``make_dataset <overrides>`` in this process (the Hydra app itself): (exit status, stdout, stderr)."""
    from torchrl_wbrm.cli import make_dataset

    monkeypatch.setattr(sys, "argv", ["make_dataset", *overrides])
    try:
        make_dataset()
        code = 0
    except SystemExit as exit_:
        code = exit_.code
    out, err = capsys.readouterr()
    return code, out, err


def test_make_dataset_command_refuses_an_existing_id_in_one_line(tmp_path, monkeypatch, capsys):
    code, out, err = make_dataset_here(monkeypatch, capsys, *TINY_LQR_DATA, "format=minari", f"out={tmp_path}")
    assert code == 0, err
    again = recipe(*TINY_LQR_DATA, "format=minari", f"out={tmp_path}", script="make_dataset.py")
    assert again.returncode == 2 and again.stdout == ""
    assert again.stderr.strip().count("\n") == 0 and "Traceback" not in again.stderr
    assert "'make_dataset/lqr_exp1_seed0/expert-v0' already exists" in again.stderr
    code, out, err = make_dataset_here(monkeypatch, capsys, *TINY_LQR_DATA, "format=minari", f"out={tmp_path}",
                                       "overwrite=true")
    assert code == 0 and "replaced the old one: overwrite=true" in out, err


def test_make_dataset_refuses_an_existing_dataset_unless_overwrite(tmp_path, monkeypatch, capsys):
    """``out=ds`` twice is refused; ``overwrite=true`` replaces it; a non-empty folder holding no dataset is never
    written into; and none of that leaves anything but the dataset on disk."""
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    code, out, err = make_dataset_here(monkeypatch, capsys, *TINY_LQR_DATA, "out=ds")
    assert code == 0, err
    meta = json.loads((work / "ds" / "metadata.json").read_text())
    code, out, err = make_dataset_here(monkeypatch, capsys, *TINY_LQR_DATA, "seed=1", "out=ds")
    assert code == 2 and "already holds a dataset" in err and "overwrite=true" in err and out == ""
    assert err.strip().count("\n") == 0
    assert json.loads((work / "ds" / "metadata.json").read_text()) == meta  # untouched
    code, out, err = make_dataset_here(monkeypatch, capsys, *TINY_LQR_DATA, "seed=1", "out=ds", "overwrite=true")
    assert code == 0 and "replaced the dataset there" in out, err
    new_meta = json.loads((work / "ds" / "metadata.json").read_text())
    assert new_meta["files"] != meta["files"]  # seed 1's data, not seed 0's
    (work / "mine").mkdir()
    (work / "mine" / "notes.txt").write_text("the user's own")
    for extra in ([], ["overwrite=true"]):
        code, out, err = make_dataset_here(monkeypatch, capsys, *TINY_LQR_DATA, "out=mine", *extra)
        assert code == 2 and "holds no dataset (notes.txt)" in err, err
    assert sorted(p.name for p in (work / "mine").iterdir()) == ["notes.txt"]
    assert sorted(p.name for p in work.iterdir()) == ["ds", "mine"]  # no outputs/ folder, no .log
