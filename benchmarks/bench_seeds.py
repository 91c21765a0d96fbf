"""Five seeds two ways: one after another in one process (``seeds=[...]``), and one process per seed.

    python benchmarks/bench_seeds.py                          # 5 seeds, 2×64 and 2×256, small budgets
    python benchmarks/bench_seeds.py --q-steps 3000 --ratio-steps 1500   # the recipe's budgets

Everything is measured in this one invocation, with one torch thread (``OMP_NUM_THREADS=1``, ``threads=1``), for each
width ``2×W`` (``q.num_cells`` and ``q.actor_num_cells``) on the same budget:

1. **one after another**: ``python recipes/wbrm_offline.py seeds=[0,...,4]``, one process, each seed's run after
   the other's (:func:`~torchrl_wbrm.training.seeds.run_seeds`);
2. **separate processes**: ``python recipes/wbrm_offline.py seed=s`` for each seed, one process after another.

The yardstick is (1): every wall time (process start-up included) is printed with its ratio to it, and where the
one-process run's time goes (its own ``results.json`` timing). Each seed's final regret of (1) is compared with
(2)'s.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "recipes" / "wbrm_offline.py"
_ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}


def widths(width: int) -> list[str]:
    return [f"q.num_cells=[{width},{width}]", f"q.actor_num_cells=[{width},{width}]"]


def _timed(command: list[str], cwd: Path) -> float:
    """Wall seconds of one process (start-up included)."""
    start = time.perf_counter()
    proc = subprocess.run(command, cwd=cwd, capture_output=True, text=True, env=_ENV)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{proc.stderr[-3000:]}")
    return wall


def recipe(args: list[str], run_dir: Path) -> float:
    return _timed([sys.executable, str(RECIPE), *args, f"hydra.run.dir={run_dir}"], run_dir.parent)


def _final(run_dir: Path, seed: int | None = None) -> dict:
    path = run_dir / "results.json" if seed is None else run_dir / f"seed{seed}" / "results.json"
    return json.loads(path.read_text())


def bench(width: int, seeds: list[int], budget: list[str], out: Path) -> dict:
    overrides = [*budget, *widths(width)]
    listed = f"seeds=[{','.join(map(str, seeds))}]"
    walls, timing, regrets = {}, {}, {}
    name = "one after another"
    walls[name] = recipe([listed, *overrides], out / f"w{width}_together")
    results = _final(out / f"w{width}_together")
    timing[name] = {**results["timing"], "process start-up and imports": walls[name] - results["wall_seconds"]}
    regrets[name] = [r["final"].get("regret") for r in results["runs"]]
    walls["separate processes"], inside, regrets["separate processes"] = 0.0, 0.0, []
    for seed in seeds:
        run_dir = out / f"w{width}_seed{seed}"
        walls["separate processes"] += recipe([f"seed={seed}", *overrides], run_dir)
        results = _final(run_dir)
        inside += results["wall_seconds"]
        regrets["separate processes"].append(results["final"].get("regret"))
    return {"width": width, "walls": walls, "timing": timing, "regrets": regrets,
            "separate_start_up_s": walls["separate processes"] - inside}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--widths", type=int, nargs="+", default=[64, 256])
    parser.add_argument("--q-steps", type=int, default=300)
    parser.add_argument("--ratio-steps", type=int, default=200)
    parser.add_argument("--eval-every", type=int, default=150)
    args = parser.parse_args()
    seeds = list(range(args.seeds))
    budget = [f"q.steps={args.q_steps}", f"ratio.steps={args.ratio_steps}", f"q.eval_every={args.eval_every}",
              "threads=1", "logger.backend="]
    print(f"{len(seeds)} seeds two ways, one torch thread, {os.cpu_count()} CPUs, load average "
          f"{', '.join(f'{x:.1f}' for x in os.getloadavg())}; budget {' '.join(budget)}")
    yardstick = "one after another"
    with tempfile.TemporaryDirectory() as tmp:
        for width in args.widths:
            r = bench(width, seeds, budget, Path(tmp))
            print(f"\n2x{width}  (ratio: wall time / wall time of {yardstick!r} in one process)")
            for name, wall in r["walls"].items():
                mean = sum(r["regrets"][name]) / len(seeds)
                print(f"  {name:<20} {wall:7.1f} s   ratio {wall / r['walls'][yardstick]:.2f}x   "
                      f"mean regret {mean:.6g}")
            exact = {name: r["regrets"][name] == r["regrets"]["separate processes"] for name in r["timing"]}
            print(f"  each seed's regret equal to its separate run's: "
                  f"{', '.join(f'{k}: {v}' for k, v in exact.items())}")
            print(f"  separate processes: {r['separate_start_up_s']:.1f} s of it process start-up and imports")
            print(f"  where the time of {yardstick!r} goes:")
            for part, seconds in r["timing"][yardstick].items():
                if part != "total":
                    print(f"    {part:<30} {seconds:7.2f} s")
    print(f"\nload average at the end: {', '.join(f'{x:.1f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
