"""Where a run's time goes, and what reading a Minari dataset costs with and without the transitions cache.

    python benchmarks/profile_run.py env=minari env.minari.data_path=datasets/benchmark \
        env.minari.expert=benchmark/hopper/expert-pool-v0 env.minari.behaviour=benchmark/hopper/random-expert05-v0 \
        env.minari.expert_episodes=5 logger=none seed=0
    python benchmarks/profile_run.py --read benchmark/hopper/random-expert05-v0 --data-path datasets/benchmark

The first runs the recipe with those overrides under ``cProfile`` (one torch thread; the run goes to a temporary
folder) and prints the seconds spent reading the data, in stage 1's steps, in stage 2's updates and in the
evaluations, with their shares of the whole. The second times one read of the dataset's episodes without the
cache (``read_minari_transitions``) and one load of its cache (``read_dataset_transitions``, writing the cache
first where there is none).
"""
from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "recipes"))

#: the phases printed: name -> (file suffix, function name) of the call whose cumulative time is the phase's
PHASES = {
    "data read": ("training/parts.py", "load_run_data"),
    "stage 1 steps": ("ratio/fitting.py", "step"),
    "stage 2 updates": ("training/trainer.py", "_q_step"),
    "evaluations": ("training/trainer.py", "_evaluate_at"),
}


def profile_run(overrides: list[str]) -> None:
    from studies.runs import run_overrides

    with tempfile.TemporaryDirectory() as run_dir:
        profile = cProfile.Profile()
        start = time.perf_counter()
        profile.enable()
        results = run_overrides(overrides, run_dir)
        profile.disable()
        total = time.perf_counter() - start
    stats = pstats.Stats(profile).stats
    print(f"whole run under the profiler: {total:.1f} s; normalised score "
          f"{results['final'].get('normalised_score', float('nan')):.1f}")
    for phase, (suffix, function) in PHASES.items():
        seconds = sum(entry[3] for (file, _, name), entry in stats.items()
                      if name == function and file.replace("\\", "/").endswith(suffix))
        print(f"{phase:>16}: {seconds:7.1f} s ({100 * seconds / total:4.1f}%)")


def time_read(dataset: str, data_path: str | None) -> None:
    from torchrl_wbrm.data.minari_data import (TRANSITIONS_CACHE, _open, read_dataset_transitions,
                                               read_minari_transitions, resolve_minari_dataset)

    ds, folder = _open(dataset, data_path), resolve_minari_dataset(dataset, data_path)
    start = time.perf_counter()
    rows = read_minari_transitions(ds).batch_size[0]
    cold = time.perf_counter() - start
    if not (folder / TRANSITIONS_CACHE).is_file():
        read_dataset_transitions(ds, folder)  # writes the cache
    start = time.perf_counter()
    read_dataset_transitions(ds, folder)
    warm = time.perf_counter() - start
    print(f"{dataset}: {ds.total_episodes} episodes, {rows} transitions; read {cold:.2f} s, from the cache "
          f"{warm:.2f} s")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="the recipe's overrides (profile a run)")
    parser.add_argument("--read", metavar="DATASET", help="time reading this Minari dataset instead")
    parser.add_argument("--data-path", default=None, help="where --read's id is looked up")
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    if args.read:
        time_read(args.read, args.data_path)
    else:
        profile_run(args.overrides)


if __name__ == "__main__":
    main()
