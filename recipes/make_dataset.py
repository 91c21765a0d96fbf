"""Collect an offline dataset (D, S^b, S^e) with torchrl's Collector, save it and print what it holds.

    python recipes/make_dataset.py                       # LQR exp1, seed 0
    python recipes/make_dataset.py env=mountain_car      # paper sizes: 20K expert, 100K behaviour
    python recipes/make_dataset.py env=mountain_car format=minari out=datasets/minari
        # the same data as two Minari datasets, mountain_car/expert-v0 and mountain_car/behaviour-v0, under the
        # Minari data path datasets/minari; read them back with env=minari (see the README, "Your own data: Minari")

``format=minari`` writes the collections the sets are made from, as whole episodes: the expert's (S^e's episodes,
with their rewards and next observations) and the behaviour's (D's and S^b's episodes together). MountainCar's
datasets record ``MountainCarContinuous-v0`` as their env; the LQR systems are not gymnasium envs, so theirs record
the spaces only (evaluate them with this project's LQR envs).
"""
from __future__ import annotations

import time
from pathlib import Path

import hydra
from hydra.utils import get_original_cwd
from omegaconf import DictConfig

from torchrl_wbrm.data.tasks import get_task
from torchrl_wbrm.training.config import register_configs

register_configs()


def _write_minari(cfg, out: Path) -> None:
    from torchrl_wbrm.data.minari_data import transitions_to_episodes, write_minari_dataset

    task = get_task(cfg.env)
    datasets, behaviour, expert = task.recorded_collections(seed=cfg.seed, storage=cfg.storage)
    sizes = datasets.sizes()
    if behaviour.shape[0] != sizes["transitions"] + sizes["behaviour_samples"] or expert.shape[0] != sizes["expert_samples"]:
        raise RuntimeError(f"The recorded collections ({behaviour.shape[0]} behaviour, {expert.shape[0]} expert "
                           f"steps) are not the sets' {sizes}.")
    namespace = cfg.minari_namespace or cfg.env.name
    kind = cfg.env.kind
    env_kwargs = task.minari_env_kwargs(behaviour)  # a gymnasium id, or (LQR) the spaces only
    written = {}
    for part, data in (("expert", expert), ("behaviour", behaviour)):
        dataset_id = f"{namespace}/{part}-v0"
        ds = write_minari_dataset(dataset_id, transitions_to_episodes(data), data_path=out,
                                  algorithm_name=f"torchrl_wbrm {kind} {part} policy, seed {cfg.seed}",
                                  description=f"torchrl_wbrm {cfg.env.name} {part} data (recipes/make_dataset.py)",
                                  **env_kwargs)
        written[dataset_id] = (ds.total_episodes, ds.total_steps)
    print(datasets.summary())
    for dataset_id, (episodes, steps) in written.items():
        print(f"Minari dataset {dataset_id}: {episodes} episodes, {steps} steps")
    print(f"saved under the Minari data path {out}")


@hydra.main(config_path="../configs", config_name="make_dataset", version_base="1.3")
def main(cfg: DictConfig) -> None:
    start = time.perf_counter()
    if cfg.format not in ("torchrl", "minari"):
        raise ValueError(f"format={cfg.format!r} is not allowed: choose 'torchrl' or 'minari'.")
    task = get_task(cfg.env)
    if not task.collects_data:
        raise ValueError(f"env={cfg.env.name} (env.kind={cfg.env.kind}) reads its datasets; make_dataset collects "
                         f"the project's own envs.")
    out = Path(cfg.out)
    if not out.is_absolute():
        out = Path(get_original_cwd()) / out
    if cfg.format == "minari":
        _write_minari(cfg, out)
        print(f"env: {cfg.env.name}  seed: {cfg.seed}  ({time.perf_counter() - start:.1f} s)")
        return
    datasets = task.make_datasets(seed=cfg.seed, storage=cfg.storage)
    datasets.save(out)
    print(f"env: {cfg.env.name}  seed: {cfg.seed}  ({time.perf_counter() - start:.1f} s)")
    print(datasets.summary())
    if "optimal_return" in datasets.metadata:
        print(f"optimal_return (exact): {datasets.metadata['optimal_return']:.4f}")
    print(f"saved to {out}")


if __name__ == "__main__":
    main()
