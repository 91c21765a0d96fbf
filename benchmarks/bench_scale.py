"""Scale: a 10 M-transition LQR behaviour dataset streamed into a ``LazyMemmapStorage``, then 1,000 batches of 256.

    python benchmarks/bench_scale.py                                  # 10 M transitions in a temporary directory
    python benchmarks/bench_scale.py --out datasets/lqr_10m           # keep the storage (a folder of memmaps)
    python benchmarks/bench_scale.py --transitions 1000000 --compare 0

The behaviour policy of the recipe's data (``a = −0.5 K x + N(0, 0.5² I)`` on LQR exp1) runs in ``LQREnv`` batches of
``--chunk-envs`` systems for one 20-step episode each; every chunk (``chunk-envs × 20`` transitions) is flattened,
given episode ids and written into the memmap storage with ``ReplayBuffer.extend``, then dropped: the whole set is
never in memory. Printed: build time, peak RSS of the process (``ru_maxrss``, which counts the memmap pages it
touched), sampling throughput through ``buffer.sample()`` and through the trainer's ``BufferBatches``, and the same
against a ``LazyTensorStorage`` (in RAM) of ``--compare`` transitions.
"""
from __future__ import annotations

import argparse
import os
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

import torch
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer

sys.path.insert(0, os.path.dirname(__file__))
from _timing import single_thread  # noqa: E402

from torchrl_wbrm.envs import LQREnv  # noqa: E402
from torchrl_wbrm.policies import make_lqr_behaviour  # noqa: E402
from torchrl_wbrm.data.sampling import BufferBatches  # noqa: E402


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB on Linux


def stream_into(storage, transitions: int, chunk_envs: int, seed: int = 0) -> tuple[TensorDictReplayBuffer, float]:
    env = LQREnv("exp1", batch_size=[chunk_envs], seed=seed)
    policy = make_lqr_behaviour(env, gain_scale=0.5, noise_std=0.5)
    horizon = env.config.horizon
    buffer = TensorDictReplayBuffer(storage=storage, batch_size=256)
    written, episode = 0, 0
    start = time.perf_counter()
    with torch.no_grad():
        while written < transitions:
            chunk = env.rollout(horizon, policy)  # [chunk_envs, 20]
            chunk.names = None
            chunk.set("episode", (episode + torch.arange(chunk_envs)).unsqueeze(-1).expand(chunk_envs, horizon))
            flat = chunk.reshape(-1)[: transitions - written]
            buffer.extend(flat)
            written += flat.shape[0]
            episode += chunk_envs
            del chunk, flat
    return buffer, time.perf_counter() - start


def sampling(buffer, batches: int) -> dict:
    fast = BufferBatches(buffer)
    out = {}
    for name, draw in (("buffer.sample()", buffer.sample), ("BufferBatches.sample()", fast.sample)):
        draw()
        start = time.perf_counter()
        for _ in range(batches):
            batch = draw()
        out[name] = batches / (time.perf_counter() - start)
        assert batch.shape[0] == 256
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--transitions", type=int, default=10_000_000)
    parser.add_argument("--chunk-envs", type=int, default=25_000)
    parser.add_argument("--batches", type=int, default=1000)
    parser.add_argument("--compare", type=int, default=1_000_000, help="LazyTensorStorage size (0: skip)")
    parser.add_argument("--out", default=None, help="keep the memmap storage in this folder")
    args = parser.parse_args(argv)
    single_thread()
    rss_start = peak_rss_mb()
    tmp = None
    if args.out is None:
        tmp = tempfile.mkdtemp(prefix="wbrm_scale_")
        scratch = Path(tmp) / "transitions"
    else:
        scratch = Path(args.out)
    try:
        storage = LazyMemmapStorage(args.transitions, scratch_dir=scratch)
        buffer, build = stream_into(storage, args.transitions, args.chunk_envs)
        rss_build = peak_rss_mb()
        rates = sampling(buffer, args.batches)
        rss_sample = peak_rss_mb()
        size = sum(f.stat().st_size for f in scratch.rglob("*") if f.is_file()) / 2**20
        print(f"LazyMemmapStorage, {args.transitions:,} transitions ({size:,.0f} MiB on disk at {scratch}):")
        print(f"  build (collect + write, chunks of {args.chunk_envs * 20:,}): {build:.1f} s "
              f"({args.transitions / build / 1e6:.2f} M transitions/s)")
        print(f"  peak RSS: {rss_start:.0f} MB after imports, {rss_build:.0f} MB after the build, "
              f"{rss_sample:.0f} MB after sampling (goal < 1500 MB)")
        for name, rate in rates.items():
            print(f"  {args.batches} batches of 256 via {name}: {rate:,.0f} batches/s")
        del buffer, storage
        if args.compare:
            ram = LazyTensorStorage(args.compare)
            ram_buffer, ram_build = stream_into(ram, args.compare, args.chunk_envs)
            ram_rates = sampling(ram_buffer, args.batches)
            print(f"LazyTensorStorage (RAM), {args.compare:,} transitions: build {ram_build:.1f} s")
            for name, rate in ram_rates.items():
                print(f"  {args.batches} batches of 256 via {name}: {rate:,.0f} batches/s "
                      f"(memmap at {args.transitions:,}: {rates[name] / rate:.2f}x)")
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
