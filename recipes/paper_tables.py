"""The paper's Tables 2 and 3, regenerated on identical data with seeds and confidence intervals.

    python recipes/paper_tables.py                    # all algorithms x {LQR exp1-3, MountainCar} x 5 seeds
    python recipes/paper_tables.py --quick            # a smoke version (CI)
    python recipes/paper_tables.py --algos wbrm td3bc --envs lqr_exp1 --seeds 3
    python recipes/paper_tables.py --report-only      # rebuild tables.md and paper_tables.png from finished runs

The table budget (``TABLE_BUDGET``, the same for every algorithm, to fit the whole grid in an hour on 2 cores):
2×128 networks and 2,000 steps (the main recipe's default is 2×256 and 3,000), CQL with 4 random actions per state
(torchrl's default 10 made CQL alone take half the hour). Everything else is ``configs/wbrm_offline.yaml``.

It launches one Hydra multirun of ``recipes/wbrm_offline.py`` per environment through the local joblib launcher
(``algo=...`` x ``seed=...``; every algorithm sees the same data for a given seed, collected once into a
``data_cache``), then writes ``tables.md``:
Table 2 (LQR: mean 20-step discounted return ± 95% CI per algorithm and experiment, beside the exact optimum and the
paper's figures), the paired regret, Q̂'s error relative to Q*'s spread and Q̂'s overestimation bias
mean(Q̂ − Q*) on behaviour and expert data, and Table 3 (MountainCar: mean return over 100 episodes ± 95% CI).
"""
from __future__ import annotations

import argparse
import json
import os
import time
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAPER_TABLE_2 = {  # Table 2 of the paper (one run each, no error bars)
    "dqn": (85.09, 84.32, 84.57),
    "ddpg": (84.74, 85.49, 86.20),
    "mabo": (85.02, 85.64, 84.64),
    "wbrm": (86.65, 86.74, 87.10),
}
PAPER_TABLE_3 = {"dqn": 94.67, "ddpg": 95.29, "mabo": 94.78, "wbrm": 95.51}
TABLE_BUDGET = [
    "q.num_cells=[128,128]", "q.actor_num_cells=[128,128]", "q.steps=2000", "q.eval_every=1000",
    "eval.train_episodes=200", "baselines.cql.num_random=4",
]
QUICK = [
    "env.lqr_data.behaviour_episodes=40", "env.lqr_data.expert_episodes=20", "env.lqr_data.parallel_envs=20",
    "env.mountain_car_data.expert_transitions=300", "env.mountain_car_data.behaviour_transitions=1200",
    "ratio.steps=10", "ratio.eval_every=5", "ratio.batch_size=64", "q.steps=10", "q.eval_every=10",
    "q.num_cells=[16,16]", "q.actor_num_cells=[16,16]", "eval.episodes=20", "eval.train_episodes=1",
    "eval.q_samples=200",
]


def available_algos() -> list[str]:
    return sorted(p.stem for p in (ROOT / "configs" / "algo").glob("*.yaml"))


def launch(env: str, algos: list[str], seeds: int, out: Path, jobs: int, extra: list[str], quick: bool,
           launcher: str = "joblib", launcher_args: list[str] = ()) -> None:
    if env == "mountain_car":  # the paper's 100 evaluation episodes (2 in the smoke version); 5 at training time
        extra = [o for o in extra if not o.startswith(("eval.episodes=", "eval.train_episodes="))]
        extra += [f"eval.episodes={2 if quick else 100}", f"eval.train_episodes={1 if quick else 5}"]
    cmd = [
        sys.executable, str(ROOT / "recipes" / "wbrm_offline.py"), "-m",
        f"hydra/launcher={launcher}", *([f"hydra.launcher.n_jobs={jobs}"] if launcher == "joblib" else []),
        *launcher_args, "threads=1",
        f"env={env}", f"algo={','.join(algos)}", f"seed={','.join(str(s) for s in range(seeds))}",
        "logger=none", "plots=false", "checkpoint_every=0", f"data_cache={out / 'data_cache'}",
        f"hydra.sweep.dir={out / env}", "hydra.sweep.subdir=${algo}_seed${seed}",
        *extra,
    ]
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, cwd=ROOT, env={**os.environ, "MPLBACKEND": "Agg"})


def tables(out: Path) -> str:
    from torchrl_wbrm.training.reporting import ci_cell, load_results

    records = load_results(out)
    by = {}
    for r in records:
        by.setdefault((r.get("algo", "wbrm"), r["env"]), []).append(r)
    algos = sorted({a for a, _ in by})
    lqr_envs = [e for e in ("lqr_exp1", "lqr_exp2", "lqr_exp3") if any(env == e for _, env in by)]

    def cell(algo, env, path, digits=3):
        return ci_cell(by.get((algo, env), []), path, digits)

    parts = []
    if lqr_envs:
        optimum = {e: next(r["final"]["optimal_return_exact"] for (a, env), rs in by.items() if env == e for r in rs)
                   for e in lqr_envs}
        head = "| algorithm | " + " | ".join(f"{e} return" for e in lqr_envs) + " | paper (exp1, exp2, exp3) |"
        lines = [head, "|" + "---|" * (len(lqr_envs) + 2)]
        lines.append("| exact optimum | " + " | ".join(f"{optimum[e]:.3f}" for e in lqr_envs) + " | 87.84 (the reward cap) |")
        for a in algos:
            paper = ", ".join(f"{v:.2f}" for v in PAPER_TABLE_2[a]) if a in PAPER_TABLE_2 else "–"
            lines.append(f"| {a} | " + " | ".join(cell(a, e, "final.return") for e in lqr_envs) + f" | {paper} |")
        parts.append("### Table 2 (LQR): mean 20-step discounted return ± 95% CI over seeds\n\n" + "\n".join(lines))
        for title, path, digits in (
            ("paired regret against the exact optimum", "final.regret", 4),
            ("Q̂ error relative to Q*'s spread, on expert samples", "final.q_error_expert", 3),
            ("Q̂ overestimation bias mean(Q̂ − Q*), on expert samples", "final.q_bias_expert", 3),
            ("Q̂ overestimation bias mean(Q̂ − Q*), on behaviour samples", "final.q_bias_behaviour", 3),
        ):
            lines = ["| algorithm | " + " | ".join(lqr_envs) + " |", "|" + "---|" * (len(lqr_envs) + 1)]
            for a in algos:
                lines.append(f"| {a} | " + " | ".join(cell(a, e, path, digits) for e in lqr_envs) + " |")
            parts.append(f"### LQR: {title}\n\n" + "\n".join(lines))
    if any(env == "mountain_car" for _, env in by):
        lines = ["| algorithm | mean return (100 episodes) ± 95% CI over seeds | paper |", "|---|---|---|"]
        for a in algos:
            paper = f"{PAPER_TABLE_3[a]:.2f}" if a in PAPER_TABLE_3 else "–"
            lines.append(f"| {a} | {cell(a, 'mountain_car', 'final.return', 2)} | {paper} |")
        parts.append("### Table 3 (MountainCarContinuous-v0)\n\n" + "\n".join(lines))
    envs = lqr_envs + (["mountain_car"] if any(env == "mountain_car" for _, env in by) else [])
    lines = ["| algorithm | " + " | ".join(envs) + " |", "|" + "---|" * (len(envs) + 1)]
    for a in algos:
        lines.append(f"| {a} | " + " | ".join(cell(a, e, "wall_seconds", 0) for e in envs) + " |")
    parts.append("### Cost: wall seconds per run (one torch thread, two runs at a time)\n\n" + "\n".join(lines))
    seeds = sorted({r["seed"] for r in records})
    timing = out / "wall_seconds.json"
    total = f" The whole grid took {json.loads(timing.read_text())['wall_seconds'] / 60:.1f} min." if timing.is_file() else ""
    parts.append(f"Seeds: {seeds}. Paper figures are single runs without error bars.{total}")
    return "\n\n".join(parts)


def plot(out: Path) -> Path:
    """``paper_tables.png``: LQR paired regret (log scale) and MountainCar return per algorithm, mean ± 95% CI."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchrl_wbrm.training.plots import plot_ci_rows
    from torchrl_wbrm.training.reporting import load_results

    records = load_results(out)
    envs = [e for e in ("lqr_exp1", "lqr_exp2", "lqr_exp3", "mountain_car") if any(r["env"] == e for r in records)]
    algos = sorted({r.get("algo", "wbrm") for r in records})
    fig, axes = plt.subplots(1, len(envs), figsize=(4.2 * len(envs), 0.35 * len(algos) + 1.8), squeeze=False)
    for ax, env in zip(axes[0], envs):
        key = "return" if env == "mountain_car" else "regret"
        rows = {a: [r["final"][key] for r in records if r["env"] == env and r.get("algo", "wbrm") == a] for a in algos}
        plot_ci_rows(ax, rows, log=key == "regret")
        ax.set_title(f"{env}: {'return (100 episodes)' if key == 'return' else 'paired regret'}", fontsize=10)
    fig.suptitle("mean ± 95% CI over seeds (LQR: regret against the exact optimum)", fontsize=10)
    fig.tight_layout()
    path = out / "paper_tables.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algos", nargs="+", default=None, help=f"default: all of configs/algo ({available_algos()})")
    parser.add_argument("--envs", nargs="+", default=["lqr_exp1", "lqr_exp2", "lqr_exp3", "mountain_car"])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--jobs", type=int, default=2, help="parallel runs of the joblib launcher")
    parser.add_argument("--launcher", default="joblib",
                        help="Hydra launcher: joblib (local), submitit_local, submitit_slurm, ray (pip install -e '.[sweeps]')")
    parser.add_argument("--launcher-args", nargs="*", default=[],
                        help="launcher overrides, e.g. hydra.launcher.partition=cpu hydra.launcher.timeout_min=30")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--out", default="results/paper_tables")
    parser.add_argument("--report-only", action="store_true", help="only rebuild tables.md from finished runs")
    args = parser.parse_args()
    out = Path(args.out)
    algos = args.algos or available_algos()
    unknown = sorted(set(algos) - set(available_algos()))
    if unknown:
        raise SystemExit(f"Unknown algorithms {unknown}: choose from {available_algos()} (configs/algo/).")
    if not args.report_only:
        start = time.perf_counter()
        for env in args.envs:
            launch(env, algos, 1 if args.quick else args.seeds, out, args.jobs, QUICK if args.quick else TABLE_BUDGET,
                   args.quick, args.launcher, args.launcher_args)
        (out / "wall_seconds.json").write_text(json.dumps({"wall_seconds": time.perf_counter() - start,
                                                           "envs": args.envs, "algos": algos, "seeds": args.seeds}))
    text = tables(out)
    (out / "tables.md").write_text(text + "\n")
    plot(out)
    print(text)
    from torchrl_wbrm.training.logging import log_study_summary  # the group's wandb summary run (offline)

    log_study_summary("paper_tables", out, tables=[out / "tables.md"], figures=[out / "paper_tables.png"])


if __name__ == "__main__":
    main()
