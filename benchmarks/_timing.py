"""Interleaved timing: every candidate of a comparison is timed in turn within each round, in one process, and the
median over rounds is reported (with the median of the per-round ratios to the yardstick).

Timings on a shared machine drift; timing A and B in alternation and quoting the ratio of each round keeps the
comparison honest when the absolute figures do not hold still.
"""
from __future__ import annotations

import statistics
import time
from typing import Callable

import torch

__all__ = ["compare", "print_comparison", "single_thread"]


def single_thread() -> None:
    """One intra-op thread, as the figures in the README were measured."""
    torch.set_num_threads(1)


def _time(fn: Callable[[], object], iterations: int, sync: Callable[[], None] | None) -> float:
    if sync is not None:
        sync()
    start = time.perf_counter()
    for _ in range(iterations):
        fn()
    if sync is not None:
        sync()
    return (time.perf_counter() - start) / iterations


def compare(
    candidates: dict[str, Callable[[], object]],
    *,
    yardstick: str,
    iterations: int = 50,
    rounds: int = 7,
    warmup: int = 10,
    sync: Callable[[], None] | None = None,
) -> dict[str, dict[str, float]]:
    """Time every callable of ``candidates`` ``rounds`` times, interleaved (A B C A B C ...), ``iterations`` calls each.

    Returns ``name -> {"median_s", "min_s", "ratio"}`` where ``ratio`` is the median over rounds of
    ``time(name) / time(yardstick)`` within the same round. ``sync`` (e.g. ``torch.cuda.synchronize``) is called
    before and after each timed block.
    """
    if yardstick not in candidates:
        raise KeyError(f"yardstick {yardstick!r} is not among the candidates {list(candidates)}.")
    for fn in candidates.values():
        for _ in range(warmup):
            fn()
    times: dict[str, list[float]] = {name: [] for name in candidates}
    for r in range(rounds):
        names = list(candidates) if r % 2 == 0 else list(reversed(candidates))  # alternate the order too
        for name in names:
            times[name].append(_time(candidates[name], iterations, sync))
    out = {}
    for name, ts in times.items():
        ratios = [t / y for t, y in zip(ts, times[yardstick])]
        out[name] = {"median_s": statistics.median(ts), "min_s": min(ts), "ratio": statistics.median(ratios)}
    return out


def print_comparison(title: str, results: dict[str, dict[str, float]], *, unit: str = "ms", per: str = "step",
                     yardstick: str | None = None) -> None:
    scale = {"ms": 1e3, "us": 1e6, "s": 1.0}[unit]
    print(f"\n{title}" + (f"  (ratio: median over rounds of time / time of {yardstick!r})" if yardstick else ""))
    width = max(len(n) for n in results)
    for name, r in results.items():
        print(f"  {name:<{width}}  {r['median_s'] * scale:8.3f} {unit}/{per}  (min {r['min_s'] * scale:.3f})"
              f"   ratio {r['ratio']:.2f}x")
