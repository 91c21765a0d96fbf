"""The stage-2 network widths measured: the default recipe at ``q.num_cells=[W,W] q.actor_num_cells=[W,W]`` for
each task and width, every seed in one process, and a Markdown table of what each width learns and what it costs.

    python benchmarks/widths.py --data-path /tmp/widths/data --out /tmp/widths/runs
    python benchmarks/widths.py --tasks pendulum lqr_exp1 --widths 64 256 --seeds 0 1 2 --out /tmp/widths/runs

Tasks are the benchmark's Minari tasks (``pendulum``, ``mountain_car``, ``lunar_lander``, ``inverted_pendulum``:
:data:`torchrl_wbrm.data.benchmark.BENCHMARK_TASKS`) and ``lqr_exp1``. A benchmark task runs the recipe with its
dataset keys only::

    python recipes/wbrm_offline.py env=minari env.minari.data_path=<data path> \\
        env.minari.expert=benchmark/<task>/expert-v0 env.minari.behaviour=benchmark/<task>/behaviour-v0 \\
        seeds=[0,1,2] q.num_cells=[W,W] q.actor_num_cells=[W,W] logger=none hydra.run.dir=<out>/<task>_w<W>

and ``lqr_exp1`` runs ``env=lqr_exp1`` with the same seeds and widths. Every other setting (``ratio.num_cells``
included) is the recipe's default, and the recipe runs with one torch thread (``threads=1``, ``OMP_NUM_THREADS=1``).
The runs go one after another, never side by side. The datasets are written first (``python -m
torchrl_wbrm.data.benchmark``) when the data path does not hold them.

Each cell of the table is the mean ± 95% Student-t interval over the seeds of the run's final figure (the recipe's
own ``aggregate`` in ``results.json``): the normalised score (0 = uniform random actions, 100 = the dataset's
expert; higher is better) for a benchmark task, the paired regret against the exact optimum (lower is better) for
``lqr_exp1``. Below it: each seed's figure, the seeds that diverged or raised a flag, the wall time and the CPU
time (user + system) of the recipe process, and the seconds it spent in the stage-2 updates and in the stage-2
evaluations (the recipe's own ``timing``, wall seconds). The load average (1 minute) before and after each run is
printed with it: on a shared machine the wall times are only comparable at similar load; the CPU time depends on it
much less.

A run directory that already holds a ``results.json`` is read, not run again (``--rerun`` runs it again), so an
interrupted measurement resumes where it stopped. ``<out>/widths.json`` holds every cell; ``<out>/widths.md`` the
table.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "recipes" / "wbrm_offline.py"
BENCHMARK_TASKS = ("pendulum", "mountain_car", "lunar_lander", "inverted_pendulum")
LQR_TASKS = ("lqr_exp1",)
NAMESPACE = "benchmark"


def _env() -> dict:
    return {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "MPLBACKEND": "Agg"}


def task_overrides(task: str, data_path: str) -> list[str]:
    """The recipe's overrides that choose ``task``'s data."""
    if task in LQR_TASKS:
        return [f"env={task}"]
    if task not in BENCHMARK_TASKS:
        raise SystemExit(f"unknown task {task!r}: choose from {', '.join(BENCHMARK_TASKS + LQR_TASKS)}")
    return ["env=minari", f"env.minari.data_path={data_path}",
            f"env.minari.expert={NAMESPACE}/{task}/expert-v0",
            f"env.minari.behaviour={NAMESPACE}/{task}/behaviour-v0"]


def width_overrides(width: int) -> list[str]:
    return [f"q.num_cells=[{width},{width}]", f"q.actor_num_cells=[{width},{width}]"]


def ensure_data(data_path: str, tasks: list[str]) -> None:
    """Write the benchmark datasets of ``tasks`` that ``data_path`` does not hold yet."""
    missing = [t for t in tasks if t in BENCHMARK_TASKS
               and not all((Path(data_path) / NAMESPACE / t / name).is_dir() for name in ("expert-v0", "behaviour-v0"))]
    if not missing:
        return
    print(f"writing the benchmark datasets of {', '.join(missing)} under {data_path}", flush=True)
    subprocess.run([sys.executable, "-m", "torchrl_wbrm.data.benchmark", "--data-path", data_path,
                    "--tasks", *missing], check=True, env=_env())


def run_cell(task: str, width: int, seeds: list[int], data_path: str, out: Path, *, rerun: bool,
             minari_overrides: tuple[str, ...] = ()) -> dict:
    """One recipe process for ``task`` at width ``width`` (every seed in it); its figures, wall time and load.
    ``minari_overrides``: recipe overrides for a benchmark (Minari) task's run, after the width's."""
    run_dir = out / f"{task}_w{width}"
    record_path = run_dir / "widths_run.json"
    if not rerun and (run_dir / "results.json").is_file():
        record = json.loads(record_path.read_text()) if record_path.is_file() else {}
        return {**record, **summarise(task, width, json.loads((run_dir / "results.json").read_text()))}
    if run_dir.exists() and any(run_dir.iterdir()):
        stamp = time.strftime("%Y%m%d-%H%M%S")
        run_dir.rename(run_dir.with_name(f"{run_dir.name}.old-{stamp}"))
    args = [*task_overrides(task, data_path), f"seeds=[{','.join(str(s) for s in seeds)}]",
            *width_overrides(width), *(minari_overrides if task in BENCHMARK_TASKS else ()), "threads=1",
            "logger=none", f"hydra.run.dir={run_dir}"]
    print(f"\n{task} 2x{width}: python recipes/wbrm_offline.py {' '.join(args)}", flush=True)
    load_before = os.getloadavg()[0]
    cpu_before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, str(RECIPE), *args], cwd=ROOT, env=_env(),
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    wall = time.perf_counter() - start
    load_after = os.getloadavg()[0]
    cpu_after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (cpu_after.ru_utime - cpu_before.ru_utime) + (cpu_after.ru_stime - cpu_before.ru_stime)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "widths_run.log").write_text(proc.stdout)
    record = {"wall_s": wall, "cpu_s": cpu, "load_before": load_before, "load_after": load_after,
              "returncode": proc.returncode,
              "command": f"python recipes/wbrm_offline.py {' '.join(args)}"}
    record_path.write_text(json.dumps(record, indent=2))
    if proc.returncode != 0 or not (run_dir / "results.json").is_file():
        print(proc.stdout[-3000:], file=sys.stderr)
        return {**record, "task": task, "width": width, "error": f"exit status {proc.returncode}"}
    cell = {**record, **summarise(task, width, json.loads((run_dir / "results.json").read_text()))}
    print(f"  {format_cell(cell)}; per seed {format_seeds(cell)}; {wall:.0f} s wall, {cpu:.0f} s CPU "
          f"(load {load_before:.1f} → {load_after:.1f})", flush=True)
    return cell


def summarise(task: str, width: int, results: dict) -> dict:
    """The figures of one multi-seed ``results.json``."""
    figure = "regret" if task in LQR_TASKS else "normalised_score"
    agg = (results.get("aggregate") or {}).get("final", {}).get(figure) or {}
    per_seed, flags = {}, {}
    for run in results.get("runs", []):
        value = (run.get("final") or {}).get(figure)
        per_seed[int(run["seed"])] = value if isinstance(value, (int, float)) else None
        run_flags = list(run.get("flags") or [])
        if run.get("status", "finished") != "finished" and "diverged" not in run_flags:
            run_flags.append(run.get("status"))
        if run_flags:
            flags[int(run["seed"])] = run_flags
    timing = results.get("timing") or {}
    return {"task": task, "width": width, "figure": figure, "mean": agg.get("mean"),
            "half_width": agg.get("half_width"), "n": agg.get("n"), "per_seed": per_seed, "flags": flags,
            "diverged": results.get("seeds_diverged", []), "vectorised": results.get("vectorised"),
            "recipe_s": timing.get("total"), "q_updates_s": timing.get("q_updates"),
            "q_evaluations_s": timing.get("q_evaluations"), "ratio_updates_s": timing.get("ratio_updates")}


def _num(value, fmt: str) -> str:
    return "n/a" if not isinstance(value, (int, float)) or not math.isfinite(value) else format(value, fmt)


def _fmt(cell: dict) -> str:
    return ".3g" if cell.get("figure") == "regret" else ".1f"


def format_cell(cell: dict) -> str:
    if "error" in cell:
        return f"failed ({cell['error']})"
    fmt = _fmt(cell)
    return f"{_num(cell['mean'], fmt)} ± {_num(cell['half_width'], fmt)}"


def format_seeds(cell: dict) -> str:
    if "error" in cell:
        return "—"
    fmt = _fmt(cell)
    parts = []
    for seed, value in sorted(cell["per_seed"].items(), key=lambda kv: int(kv[0])):
        flags = cell["flags"].get(seed) or cell["flags"].get(str(seed))
        parts.append(_num(value, fmt) + (f" ({', '.join(flags)})" if flags else ""))
    return " / ".join(parts)


def table(cells: list[dict], tasks: list[str], widths: list[int], seeds: list[int]) -> str:
    """The Markdown table: one row per task, per width the mean ± 95% CI, each seed's figure and the wall time."""
    by_key = {(c["task"], c["width"]): c for c in cells}
    head = ["task", "figure"] + [f"2×{w}" for w in widths]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for task in tasks:
        figure = "regret ↓" if task in LQR_TASKS else "normalised score ↑"
        rows = {"mean ± 95% CI": [], f"seeds {', '.join(str(s) for s in seeds)}": [], "wall time (load)": [],
                "CPU time": [],
                "stage-2 updates / evaluations": []}
        for w in widths:
            cell = by_key.get((task, w))
            if cell is None:
                for r in rows.values():
                    r.append("not run")
                continue
            rows["mean ± 95% CI"].append(format_cell(cell))
            rows[f"seeds {', '.join(str(s) for s in seeds)}"].append(format_seeds(cell))
            wall = cell.get("wall_s")
            load = cell.get("load_before"), cell.get("load_after")
            rows["wall time (load)"].append(
                "n/a" if wall is None else f"{wall:.0f} s ({_num(load[0], '.1f')}–{_num(load[1], '.1f')})")
            rows["CPU time"].append(f"{_num(cell.get('cpu_s'), '.0f')} s")
            rows["stage-2 updates / evaluations"].append(
                f"{_num(cell.get('q_updates_s'), '.0f')} s / {_num(cell.get('q_evaluations_s'), '.0f')} s")
        for i, (label, values) in enumerate(rows.items()):
            lines.append(f"| {task if i == 0 else ''} | {figure + ', ' if i == 0 else ''}{label} | "
                         + " | ".join(values) + " |")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", nargs="+", default=[*BENCHMARK_TASKS, *LQR_TASKS],
                        choices=[*BENCHMARK_TASKS, *LQR_TASKS])
    parser.add_argument("--widths", nargs="+", type=int, default=[64, 128, 256])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--data-path", default="datasets/benchmark",
                        help="Minari data path of the benchmark datasets (written there if missing)")
    parser.add_argument("--out", default="results/widths", help="folder of the run directories and the table")
    parser.add_argument("--rerun", action="store_true", help="run again the cells whose results.json exists")
    parser.add_argument("--minari-overrides", nargs="+", default=[], metavar="KEY=VALUE",
                        help="recipe overrides for the benchmark (Minari) tasks' runs, e.g. the shared defaults "
                             "q.layer_norm=false q.steps=3000 q.eval_every=500 q.select=last")
    args = parser.parse_args(argv)
    malformed = [o for o in args.minari_overrides if "=" not in o or o.startswith("=")]
    if malformed:
        parser.error(f"--minari-overrides {' '.join(malformed)}: each must be KEY=VALUE.")
    data_path = str(Path(args.data_path).resolve())
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    ensure_data(data_path, args.tasks)
    cells = []
    for task in args.tasks:
        for width in args.widths:
            cells.append(run_cell(task, width, args.seeds, data_path, out, rerun=args.rerun,
                                  minari_overrides=tuple(args.minari_overrides)))
            (out / "widths.json").write_text(json.dumps(cells, indent=2))
    text = table(cells, args.tasks, args.widths, args.seeds)
    (out / "widths.md").write_text(text + "\n")
    print("\n" + text)


if __name__ == "__main__":
    main()
