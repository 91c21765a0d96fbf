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

import sys
import time
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from torchrl_wbrm.training import WBRMTrainer, register_configs, validate_config
from torchrl_wbrm.training.guards import RunInterrupted, write_json
from torchrl_wbrm.training.logging import make_logger
from torchrl_wbrm.training.reporting import summarise

register_configs()


@hydra.main(config_path="../configs", config_name="wbrm_offline", version_base="1.3")
def main(cfg: DictConfig) -> None:
    start = time.perf_counter()
    validate_config(OmegaConf.to_object(cfg))  # every value, before any data are collected
    run_dir = Path(cfg.resume) if cfg.resume else Path(HydraConfig.get().runtime.output_dir)
    try:
        trainer = WBRMTrainer(cfg, run_dir, logger=None, resume=bool(cfg.resume))
        trainer.logger = make_logger(
            cfg.logger, run_dir, f"wbrm_{cfg.env.name}_seed{cfg.seed}", OmegaConf.to_container(cfg, resolve=True)
        )
        results = trainer.run()
    except KeyboardInterrupt:  # before training started (data collection): nothing to checkpoint
        print(f"Interrupted before training started; nothing was written to {run_dir}.", file=sys.stderr)
        sys.exit(130)
    except RunInterrupted as err:
        print(err, file=sys.stderr)
        sys.exit(err.exit_code)
    results["wall_seconds"] = time.perf_counter() - start
    write_json(run_dir / "results.json", results)
    if results.get("status") == "diverged":
        print(results["diverged"]["message"], file=sys.stderr)
        print(f"run directory: {run_dir} (results.json has status 'diverged'; checkpoint.pt is the last finite state)",
              file=sys.stderr)
        sys.exit(2)
    print(summarise(results))
    print(f"run directory: {run_dir}")


if __name__ == "__main__":
    main()
