"""Run the main recipe's config in-process from Hydra overrides (the studies' unit of work)."""
from __future__ import annotations

import json
import os
from pathlib import Path

__all__ = ["run_overrides"]

CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs"


def run_overrides(
    overrides: list[str], run_dir: str | os.PathLike, *, extra_results: dict | None = None, config_name: str = "wbrm_offline"
) -> dict:
    """Compose ``configs/<config_name>.yaml`` with ``overrides``, train with one torch thread and return the results.

    A run whose ``results.json`` exists is not run again (its results are read back), so an interrupted study
    resumes where it stopped. ``extra_results`` are merged into the saved results (e.g. the study cell's labels).
    """
    import torch
    from hydra import compose, initialize_config_dir

    from torchrl_wbrm.training.config import register_configs
    from torchrl_wbrm.training.trainer import WBRMTrainer

    run_dir = Path(run_dir)
    done = run_dir / "results.json"
    if done.is_file():
        return json.loads(done.read_text())
    torch.set_num_threads(1)
    register_configs()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose(config_name, overrides=[*overrides, "threads=1"])
    results = WBRMTrainer(cfg, run_dir, progress=False).run()
    results.update(extra_results or {})
    done.write_text(json.dumps(results, indent=2, default=float))
    return results
