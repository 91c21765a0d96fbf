"""Recipe smoke tests: each runs in a subprocess with tiny overrides, as a user would launch it."""
from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest
import torch

from tests import forked, inprocess

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow  # each test runs a recipe in a subprocess

TINY_LQR = [
    "env.lqr_data.behaviour_episodes=40",
    "env.lqr_data.expert_episodes=20",
    "env.lqr_data.parallel_envs=20",
    "ratio.steps=20",
    "ratio.eval_every=10",
    "ratio.num_cells=[16,16]",
    "q.steps=20",
    "q.eval_every=10",
    "q.num_cells=[16,16]",
    "q.actor_num_cells=[16,16]",
    "eval.offline_value=false",
    "eval.episodes=50",
    "eval.train_episodes=20",
    "eval.q_samples=400",
]
TINY_MC = [
    "env.mountain_car_data.expert_transitions=300",
    "env.mountain_car_data.behaviour_transitions=1200",
    "ratio.steps=10",
    "ratio.eval_every=5",
    "ratio.batch_size=64",
    "q.steps=10",
    "q.eval_every=10",
    "q.num_cells=[16,16]",
    "q.actor_num_cells=[16,16]",
    "eval.offline_value=false",
    "eval.episodes=1",
    "eval.train_episodes=1",
]


def run_recipe(script: str, *overrides: str, check: bool = True, process: bool = False) -> subprocess.CompletedProcess:
    """``python recipes/<script> <overrides>``: in this process (:mod:`tests.inprocess`), or with ``process`` in a
    process of its own (:mod:`tests.forked`)."""
    env = {**os.environ, "WANDB_MODE": "offline", "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1"}
    if process:
        proc = forked.run_forked(ROOT / "recipes" / script, *overrides, cwd=ROOT, env=env)
    else:
        proc = inprocess.run_script(ROOT / "recipes" / script, *overrides, cwd=ROOT, env=env)
    if check and proc.returncode != 0:
        raise AssertionError(f"{script} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


# lqr_exp1 runs every algo in tests/test_baselines.py; here one run per logger: wandb (offline) and the default csv
@pytest.mark.parametrize("env_name, logger", [("lqr_exp2", "wandb"), ("lqr_exp3", "csv")])
def test_wbrm_offline_lqr(tmp_path, env_name, logger):
    # the wandb run in a process of its own (wandb starts a service process of its own), the csv one in this one
    proc = run_recipe("wbrm_offline.py", f"env={env_name}", f"logger={logger}", *TINY_LQR, f"hydra.run.dir={tmp_path}",
                      process=logger == "wandb")
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["env"] == env_name
    assert {"regret", "regret_ci", "q_error_expert", "return"} <= results["final"].keys()
    assert "paired regret" in proc.stdout
    for name in ("training_curve.png", "evaluation.png", "checkpoint.pt", "history.json"):
        assert (tmp_path / name).is_file(), name
    if logger == "csv":
        assert any((tmp_path / "logs").rglob("*.csv"))
    else:
        assert any((tmp_path / "wandb").glob("offline-run-*")), list(tmp_path.iterdir())


def test_wbrm_offline_mountain_car(tmp_path):
    run_recipe("wbrm_offline.py", "env=mountain_car", *TINY_MC, f"hydra.run.dir={tmp_path}")
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["env"] == "mountain_car"
    assert "return" in results["final"] and "regret" not in results["final"]


def test_wbrm_offline_resume_continues_exactly(tmp_path):
    # a larger budget continues a constant learning rate; a cosine schedule's length is its budget, so there a larger
    # q.steps on resume is refused (tests/test_resume.py)
    a, b = tmp_path / "a", tmp_path / "b"
    constant = "q.lr_schedule=constant"
    run_recipe("wbrm_offline.py", *TINY_LQR, constant, "q.steps=30", "checkpoint_every=10", f"hydra.run.dir={a}",
               "plots=false")
    run_recipe("wbrm_offline.py", *TINY_LQR, constant, "q.steps=20", "checkpoint_every=10", f"hydra.run.dir={b}",
               "plots=false")
    run_recipe("wbrm_offline.py", *TINY_LQR, constant, "q.steps=30", "checkpoint_every=10", f"resume={b}",
               "plots=false")
    ca = torch.load(a / "checkpoint.pt", weights_only=True)["q_loss"]
    cb = torch.load(b / "checkpoint.pt", weights_only=True)["q_loss"]
    assert all(torch.equal(ca[k], cb[k]) for k in ca)


@pytest.mark.parametrize(
    "override, message",
    [
        ("q.residual=cubed", "q.residual='cubed' is not allowed"),  # the recipe validates before collecting data
        ("env=lqr_exp9", "lqr_exp9"),  # Hydra's own error (a misspelt key: tests/test_training.py, in process)
    ],
)
def test_wbrm_offline_config_errors(tmp_path, override, message):
    proc = run_recipe("wbrm_offline.py", override, f"hydra.run.dir={tmp_path}", check=False)
    assert proc.returncode != 0
    assert message in proc.stdout + proc.stderr


def test_make_dataset(tmp_path):
    proc = run_recipe(
        "make_dataset.py",
        "env.lqr_data.behaviour_episodes=20",
        "env.lqr_data.expert_episodes=10",
        f"out={tmp_path / 'ds'}",
        f"hydra.run.dir={tmp_path / 'hydra'}",
    )
    assert "S^e (expert state-actions for the ratio): 200" in proc.stdout
    assert (tmp_path / "ds" / "metadata.json").is_file()


def test_policy_returns_reports_what_the_dqn_grid_costs():
    """The exact optimum snapped to DQN's 21-value grid: regret 0.0558 ± 0.0028 (1,000 paired episodes, seed 0)."""
    proc = run_recipe("policy_returns.py", "--episodes", "50", "--skip-mountain-car", "--dqn-bins", "21")
    row = next(line for line in proc.stdout.splitlines() if line.startswith("| 21 (441 joint actions)"))
    regret = float(row.split("|")[2].split("±")[0])
    assert 0.04 < regret < 0.07, row
    assert "| exp1 | 85.4351 |" in proc.stdout  # the exact optimum row of the policy table
