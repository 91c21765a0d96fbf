"""Deep Weighted Bellman Residual Minimization, offline: stage 1 fits the density ratio ŵ, stage 2 fits Q*.

    python recipes/wbrm_offline.py                                  # LQR exp1, the default (about a minute)
    python recipes/wbrm_offline.py env=lqr_exp3 seed=2
    python recipes/wbrm_offline.py env=mountain_car q.gamma=0.99
    python recipes/wbrm_offline.py ratio.source=none                # the unweighted ablation
    python recipes/wbrm_offline.py algo=td3bc                       # a baseline on the same data (configs/algo/)
    python recipes/wbrm_offline.py logger=wandb                     # offline wandb run in the run directory
    python recipes/wbrm_offline.py resume=outputs/wbrm_offline/...  # continue an interrupted run exactly

Writes results.json, history.json, training_curve.png, evaluation.png, logs/ and checkpoint.pt in the run directory.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from torchrl_wbrm.training import WBRMTrainer, register_configs, validate_config
from torchrl_wbrm.training.logging import make_logger
from torchrl_wbrm.training.reporting import summarise

register_configs()


@hydra.main(config_path="../configs", config_name="wbrm_offline", version_base="1.3")
def main(cfg: DictConfig) -> None:
    start = time.perf_counter()
    validate_config(OmegaConf.to_object(cfg))
    run_dir = Path(cfg.resume) if cfg.resume else Path(HydraConfig.get().runtime.output_dir)
    logger = make_logger(
        cfg.logger, run_dir, f"wbrm_{cfg.env.name}_seed{cfg.seed}", OmegaConf.to_container(cfg, resolve=True)
    )
    trainer = WBRMTrainer(cfg, run_dir, logger=logger, resume=bool(cfg.resume))
    results = trainer.run()
    results["wall_seconds"] = time.perf_counter() - start
    (run_dir / "results.json").write_text(json.dumps(results, indent=2, default=float))
    print(summarise(results))
    print(f"run directory: {run_dir}")


if __name__ == "__main__":
    main()
