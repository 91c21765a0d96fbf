"""A run killed with SIGKILL (nothing caught, nothing flushed) and resumed with the recipe's resume command ends with
the figures of the uninterrupted run, exactly.

The kill points are made deterministic by the writers' test hook (``TORCHRL_WBRM_TEST_PAUSE_AT``,
:func:`torchrl_wbrm.training.guards.pause_for_test`): the recipe stops at the named point, says so on stderr, and
waits to be killed. Points: during stage 1 and during stage 2 (at a step), while a checkpoint is being written (its
new content on disk in the temporary file, not yet renamed), and while ``results.json`` is being written.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import torch

from torchrl_wbrm.training.guards import TEST_PAUSE_ENV

ROOT = Path(__file__).resolve().parents[1]

#: the tiny LQR run (tests/references.py's TINY_LQR) as recipe overrides, a checkpoint every 10 steps: checkpoints
#: are written at stage-1 steps 10 and 20, at the end of stage 1, at stage-2 steps 10, 20 and 30, after stage 2 and
#: when the run is done
OVERRIDES = [
    "env.lqr_data.behaviour_episodes=40", "env.lqr_data.expert_episodes=20", "env.lqr_data.parallel_envs=20",
    "ratio.steps=30", "ratio.batch_size=64", "ratio.eval_every=10", "ratio.num_cells=[16,16]",
    "q.steps=40", "q.batch_size=32", "q.eval_every=20", "q.num_cells=[16,16]", "q.actor_num_cells=[16,16]",
    "eval.episodes=50", "eval.train_episodes=20", "eval.q_samples=300", "logger=none", "plots=false",
    "checkpoint_every=10", "threads=1",
]
#: what differs between two runs of one config: wall-clock times
TIMES = ("wall_seconds", "data_seconds", "compile_seconds")
RECIPE = [sys.executable, str(ROOT / "recipes" / "wbrm_offline.py")]


def _env(pause: str | None = None) -> dict:
    env = {k: v for k, v in os.environ.items() if k != TEST_PAUSE_ENV}
    env["OMP_NUM_THREADS"] = "1"
    if pause is not None:
        env[TEST_PAUSE_ENV] = pause
    return env


def _figures(run_dir: Path) -> dict:
    """``results.json`` (but its wall-clock times, and ``config.resume``, which names the directory a resumed run
    continued) and ``history.json``."""
    results = json.loads((run_dir / "results.json").read_text())
    results["config"].pop("resume")
    return {"results": {k: v for k, v in results.items() if k not in TIMES},
            "history": json.loads((run_dir / "history.json").read_text())}


def _run_until_paused(cmd: list[str], pause: str, cwd: Path, timeout: float = 300.0) -> subprocess.Popen:
    """Start ``cmd`` with the hook set to ``pause``; return once it says it is paused there (then it waits)."""
    proc = subprocess.Popen(cmd, cwd=cwd, env=_env(pause), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    paused, lines = threading.Event(), []

    def read():
        for line in proc.stderr:
            lines.append(line)
            if line.strip() == f"{TEST_PAUSE_ENV}: paused at {pause}":
                paused.set()

    threading.Thread(target=read, daemon=True).start()
    if not paused.wait(timeout):
        proc.kill()
        proc.wait()
        pytest.fail(f"the run never paused at {pause} (exit code {proc.returncode}): {''.join(lines)[-3000:]}")
    return proc


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The run without interruption: its figures."""
    root = tmp_path_factory.mktemp("uninterrupted")
    proc = subprocess.run([*RECIPE, *OVERRIDES, f"hydra.run.dir={root / 'run'}"], cwd=root, env=_env(),
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return _figures(root / "run")


@pytest.mark.parametrize("point, written", [
    ("ratio:15", "the checkpoint of stage-1 step 10"),
    ("checkpoint.pt:2", "the checkpoint of stage-1 step 10: the one of step 20 is in checkpoint.tmp, not renamed"),
    ("q:25", "the checkpoint of stage-2 step 20"),
    ("checkpoint.pt:5", "the checkpoint of stage-2 step 10: the one of step 20 is in checkpoint.tmp, not renamed"),
    ("results.json:1", "the checkpoint of the finished run; results.json is in results.json.tmp, not renamed"),
])
def test_sigkill_then_resume_gives_the_uninterrupted_figures(uninterrupted, tmp_path, point, written):
    run_dir = tmp_path / "run"
    proc = _run_until_paused([*RECIPE, *OVERRIDES, f"hydra.run.dir={run_dir}"], point, tmp_path)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    assert not (run_dir / "results.json").exists()  # never a half-written one
    state = torch.load(run_dir / "checkpoint.pt", weights_only=True)["state"]  # complete: it reads
    expected = {"ratio:15": {"stage": "ratio", "step": 10}, "checkpoint.pt:2": {"stage": "ratio", "step": 10},
                "q:25": {"stage": "q", "step": 20}, "checkpoint.pt:5": {"stage": "q", "step": 10},
                "results.json:1": {"stage": "done", "step": 40}}[point]
    assert state == expected, written

    resumed = subprocess.run([*RECIPE, f"resume={run_dir}"], cwd=tmp_path, env=_env(), capture_output=True,
                             text=True, timeout=600)  # the command a user types: the run's overrides come back
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert _figures(run_dir) == uninterrupted
