"""Five seeds three ways: vectorised in one process, one after another in one process, and one process per seed.

    python benchmarks/bench_seeds.py                          # 5 seeds, 2×64 and 2×256, small budgets
    python benchmarks/bench_seeds.py --q-steps 3000 --ratio-steps 1500   # the recipe's budgets

Everything is measured in this one invocation, with one torch thread (``OMP_NUM_THREADS=1``, ``threads=1``), for each
width ``2×W`` (``q.num_cells`` and ``q.actor_num_cells``) on the same budget:

1. **vectorised**: ``python recipes/wbrm_offline.py seeds=[0,...,4]``, one process; the seeds' stacked parameters
   stepped under ``torch.vmap`` where the algo's registration says it is vectorisable;
2. **one after another**: the same seeds in one process, each seed's run after the other's
   (:func:`~torchrl_wbrm.training.seeds.run_seeds` with ``vectorise=False``), started as the recipe is;
3. **separate processes**: ``python recipes/wbrm_offline.py seed=s`` for each seed, one process after another.

The yardstick is (2), one after another in one process: every wall time (process start-up included) is printed
with its ratio to it, and where each in-process run's time goes (its own ``results.json`` timing). Each seed's final
figures of (1) and (2) are compared with (3)'s.
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


def one_after_another(args: list[str], run_dir: Path) -> float:
    """Wall seconds of one process that trains the seeds one after another (this file's ``--child``)."""
    return _timed([sys.executable, __file__, "--child", str(run_dir), *args], run_dir.parent)


def child(run_dir: str, overrides: list[str]) -> None:
    """The recipe's config composed with ``overrides``, its seeds trained one after another in this process."""
    sys.path.insert(0, str(ROOT))
    from hydra import compose, initialize_config_dir

    from torchrl_wbrm.configs import CONFIG_DIR
    from torchrl_wbrm.training.config import register_configs
    from torchrl_wbrm.training.seeds import run_seeds

    register_configs()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("wbrm_offline", overrides=overrides)
    start = time.perf_counter()
    results = run_seeds(cfg, run_dir, progress=False, vectorise=False)
    results["wall_seconds"] = time.perf_counter() - start
    Path(run_dir, "results.json").write_text(json.dumps(results))


def _final(run_dir: Path, seed: int | None = None) -> dict:
    path = run_dir / "results.json" if seed is None else run_dir / f"seed{seed}" / "results.json"
    return json.loads(path.read_text())


def bench(width: int, seeds: list[int], budget: list[str], out: Path) -> dict:
    overrides = [*budget, *widths(width)]
    listed = f"seeds=[{','.join(map(str, seeds))}]"
    walls, timing, regrets = {}, {}, {}
    walls["vectorised"] = recipe([listed, *overrides], out / f"w{width}_vectorised")
    walls["one after another"] = one_after_another([listed, *overrides], out / f"w{width}_sequential")
    for name, folder in (("vectorised", f"w{width}_vectorised"), ("one after another", f"w{width}_sequential")):
        results = _final(out / folder)
        timing[name] = {**results["timing"], "process start-up and imports": walls[name] - results["wall_seconds"]}
        regrets[name] = [r["final"].get("regret") for r in results["runs"]]
        if name == "vectorised" and not results["vectorised"]:
            raise RuntimeError(f"the vectorised run was not vectorised: {results['not_vectorised_because']}")
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
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args, rest = parser.parse_known_args()
    if args.child is not None:
        return child(args.child, rest)
    seeds = list(range(args.seeds))
    budget = [f"q.steps={args.q_steps}", f"ratio.steps={args.ratio_steps}", f"q.eval_every={args.eval_every}",
              "threads=1", "logger.backend="]
    print(f"{len(seeds)} seeds three ways, one torch thread, {os.cpu_count()} CPUs, load average "
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
            names = list(r["timing"])
            print(f"  where the time goes  {'':<12}" + "".join(f"{n:>20}" for n in names))
            parts = [k for k in r["timing"][names[0]] if k not in ("total",)]
            parts += [k for k in r["timing"][names[1]] if k not in parts and k != "total"]
            for part in parts:
                print(f"    {part:<30}" + "".join(f"{r['timing'][n].get(part, 0.0):19.2f}s" for n in names))
    print(f"\nload average at the end: {', '.join(f'{x:.1f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
