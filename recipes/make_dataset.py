"""Collect an offline dataset (D, S^b, S^e) with torchrl's Collector, save it and print what it holds.

    python recipes/make_dataset.py                       # LQR exp1, seed 0
    python recipes/make_dataset.py env=mountain_car      # paper sizes: 20K expert, 100K behaviour
"""
from __future__ import annotations

import time
from pathlib import Path

import hydra
from hydra.utils import get_original_cwd
from omegaconf import DictConfig, OmegaConf

from torchrl_wbrm.data import make_offline_datasets
from torchrl_wbrm.training.config import register_configs

register_configs()


@hydra.main(config_path="../configs", config_name="make_dataset", version_base="1.3")
def main(cfg: DictConfig) -> None:
    start = time.perf_counter()
    datasets = make_offline_datasets(cfg.env, seed=cfg.seed, storage=cfg.storage)
    out = Path(cfg.out)
    if not out.is_absolute():
        out = Path(get_original_cwd()) / out
    datasets.save(out)
    print(f"env: {cfg.env.name}  seed: {cfg.seed}  ({time.perf_counter() - start:.1f} s)")
    print(datasets.summary())
    if "optimal_return" in datasets.metadata:
        print(f"optimal_return (exact): {datasets.metadata['optimal_return']:.4f}")
    print(f"saved to {out}")


if __name__ == "__main__":
    main()
