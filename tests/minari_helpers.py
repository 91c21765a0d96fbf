"""Shared by test_minari.py and test_wandb.py: small Minari datasets made once per test session, and one recipe run
on them with the wandb logger (memoised in this module, so the two test files share one run)."""
from __future__ import annotations

import atexit
import functools
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: The recipe's budget on the MountainCar Minari datasets: small networks, a few hundred steps, 10 episodes.
MINARI_RUN = [
    "q.bc_alpha=2.5",
    "ratio.steps=100",
    "ratio.eval_every=50",
    "ratio.batch_size=256",
    "q.steps=300",
    "q.eval_every=150",
    "ratio.num_cells=[64,64]",
    "q.num_cells=[64,64]",
    "q.actor_num_cells=[64,64]",
    "eval.offline_value=false",
    "eval.episodes=10",
    "eval.train_episodes=3",
    "checkpoint_every=0",
]
GROUP = "test_minari_group"


@functools.lru_cache(maxsize=None)
def session_dir() -> Path:
    """A temporary folder for the session's datasets and run, removed when the test process exits."""
    path = Path(tempfile.mkdtemp(prefix="wbrm_minari_tests_"))
    atexit.register(shutil.rmtree, path, ignore_errors=True)
    return path


@functools.lru_cache(maxsize=None)
def mountain_car_datasets() -> dict:
    """``examples/mountain_car/expert-v0`` (12 expert episodes) and ``.../behaviour-v0`` (4 random episodes and 24
    noisy-expert ones) under a session folder, written with ``create_dataset_from_buffers`` (no jax)."""
    from torchrl_wbrm.data.minari_examples import make_mountain_car_datasets

    root = session_dir() / "minari"
    return {"data_path": str(root), **make_mountain_car_datasets(root, expert_episodes=12, random_episodes=4,
                                                                  noisy_expert_episodes=24, seed=0)}


def run_recipe(*overrides: str, check: bool = True) -> subprocess.CompletedProcess:
    env = {**os.environ, "WANDB_MODE": "offline", "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1"}
    env.pop("WANDB_SILENT", None)
    proc = subprocess.run([sys.executable, str(ROOT / "recipes" / "wbrm_offline.py"), *overrides], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)
    if check and proc.returncode != 0:
        raise AssertionError(f"wbrm_offline.py failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


@functools.lru_cache(maxsize=None)
def minari_wandb_run() -> tuple[Path, str, str, dict]:
    """One recipe run on the Minari datasets with ``logger=wandb`` (offline): ``(run dir, stdout, stderr, results)``."""
    data = mountain_car_datasets()
    run_dir = session_dir() / "run"
    proc = run_recipe("env=minari", f"env.minari.expert={data['expert']}", f"env.minari.behaviour={data['behaviour']}",
                      f"env.minari.data_path={data['data_path']}", *MINARI_RUN, "logger=wandb",
                      f"logger.group={GROUP}", f"hydra.run.dir={run_dir}")
    return run_dir, proc.stdout, proc.stderr, json.loads((run_dir / "results.json").read_text())


def leet(*args: str) -> str:
    """``wandb leet <args>`` (wandb's own reader of offline runs), its stdout."""
    wandb = Path(sys.executable).with_name("wandb")
    command = [str(wandb)] if wandb.is_file() else [sys.executable, "-m", "wandb"]
    proc = subprocess.run([*command, "leet", *args], capture_output=True, text=True, timeout=120)
    if proc.returncode != 0:
        raise AssertionError(f"wandb leet {' '.join(args)} failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    return proc.stdout
