"""Run the main recipe's config in-process from Hydra overrides (the studies' unit of work)."""
from __future__ import annotations

import json
import os
from pathlib import Path

__all__ = ["QUICK_BUDGET", "cell_dir", "run_cell", "run_cells", "run_overrides"]

#: The studies' smoke budget (``--quick``, run in CI): tiny LQR data, networks, budgets and evaluations.
QUICK_BUDGET = [
    "env.lqr_data.behaviour_episodes=60",
    "env.lqr_data.expert_episodes=30",
    "env.lqr_data.parallel_envs=30",
    "ratio.steps=20",
    "ratio.eval_every=10",
    "q.steps=20",
    "q.eval_every=20",
    "q.num_cells=[16,16]",
    "q.actor_num_cells=[16,16]",
    "eval.episodes=50",
    "eval.q_samples=300",
    "logger=none",
    "plots=false",
    "checkpoint_every=0",
]

CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs"


def run_overrides(
    overrides: list[str], run_dir: str | os.PathLike, *, extra_results: dict | None = None, config_name: str = "wbrm_offline"
) -> dict:
    """Compose ``configs/<config_name>.yaml`` with ``overrides``, train with one torch thread and return the results.

    A run whose ``results.json`` exists is not run again (its results are read back, a diverged run's too), and
    one with only a checkpoint resumes from it, so an interrupted study resumes where it stopped. ``extra_results``
    are merged into the saved results (e.g. the study cell's labels).
    """
    import torch
    from hydra import compose, initialize_config_dir

    from torchrl_wbrm.training.config import register_configs
    from torchrl_wbrm.training.guards import write_json
    from torchrl_wbrm.training.trainer import WBRMTrainer

    run_dir = Path(run_dir)
    done = run_dir / "results.json"
    if done.is_file():
        return json.loads(done.read_text())
    torch.set_num_threads(1)
    register_configs()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose(config_name, overrides=[*overrides, "threads=1"])
    # an interrupted cell (a checkpoint, no results) continues; its config must match the checkpoint's
    resume = (run_dir / "checkpoint.pt").is_file()
    results = WBRMTrainer(cfg, run_dir, progress=False, resume=resume).run()
    results.update(extra_results or {})
    write_json(done, results)
    return results


def cell_dir(out: str | os.PathLike, cell: dict, seed: int, *, labels=("block", "env", "setting", "method")) -> Path:
    """``out/<block>/<env>/<setting>/<method>/seed<seed>``: where one study cell's run for one seed lives."""
    name = "/".join(str(cell[k]) for k in labels).replace(" ", "_")
    return Path(out) / name / f"seed{seed}"


def run_cell(cell: dict, seed: int, budget: list[str], out: str, labels=("block", "env", "setting", "method")) -> str:
    """Run one study cell (``cell["overrides"]`` after ``budget``) for one seed; its labels go into the results
    under ``"study"``. Skipped if its results exist."""
    run_dir = cell_dir(out, cell, seed, labels=labels)
    run_overrides([*budget, *cell["overrides"], f"seed={seed}"], run_dir,
                  extra_results={"study": {k: cell[k] for k in labels}})
    return str(run_dir)


def run_cells(cells: list[dict], seeds, budget: list[str], out: str | os.PathLike, *, jobs: int = 2) -> None:
    """Every (cell, seed) in ``jobs`` parallel processes (one torch thread each), with a tqdm bar."""
    from joblib import Parallel, delayed
    from tqdm.auto import tqdm

    work = [(cell, seed) for cell in cells for seed in seeds]
    print(f"{len(work)} runs ({len(cells)} cells x {len(list(seeds))} seeds) into {out}", flush=True)
    runner = Parallel(n_jobs=jobs, return_as="generator_unordered")
    for _ in tqdm(runner(delayed(run_cell)(cell, seed, budget, str(out)) for cell, seed in work), total=len(work)):
        pass
