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
