"""The paper's Tables 2 and 3, regenerated on identical data with seeds and confidence intervals.

    python recipes/paper_tables.py                    # all algorithms x {LQR exp1-3, MountainCar} x 5 seeds
    python recipes/paper_tables.py --quick            # a smoke version (CI)
    python recipes/paper_tables.py --algos wbrm td3bc --envs lqr_exp1 --seeds 3
    python recipes/paper_tables.py --report-only      # rebuild tables.md and paper_tables.png from finished runs

The table budget is ``torchrl_wbrm.training.runs.TABLE_BUDGET`` (the same for every algorithm, to fit the whole
grid in an hour on 2 cores: 2×128 networks and 2,000 steps, CQL with 4 random actions per state; ``--quick``:
``TABLE_QUICK_BUDGET``). Everything else is ``configs/wbrm_offline.yaml``. The algorithms are the registry's
(``torchrl_wbrm.algos.ALGOS``).

Every (env, algorithm, seed) runs through the studies' shared runner (``torchrl_wbrm.training.runs.run_cells``: local
processes, or a Hydra launcher with ``--launcher``) into ``<out>/<env>/<algo>/seed<seed>``; every algorithm sees the
same data for a given seed, collected once into a ``data_cache``. Then it writes ``tables.md``:
Table 2 (LQR: mean 20-step discounted return ± 95% CI per algorithm and experiment, beside the exact optimum and the
paper's figures), the paired regret, Q̂'s error relative to Q*'s spread and Q̂'s overestimation bias
mean(Q̂ − Q*) on behaviour and expert data, and Table 3 (MountainCar: mean return over 100 episodes ± 95% CI).
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

PAPER_TABLE_2 = {  # Table 2 of the paper (one run each, no error bars)
    "dqn": (85.09, 84.32, 84.57),
    "ddpg": (84.74, 85.49, 86.20),
    "mabo": (85.02, 85.64, 84.64),
    "wbrm": (86.65, 86.74, 87.10),
}
PAPER_TABLE_3 = {"dqn": 94.67, "ddpg": 95.29, "mabo": 94.78, "wbrm": 95.51}
#: the run directory of a cell: <out>/<env>/<algo>/seed<seed>
LABELS = ("env", "method")


def available_algos() -> list[str]:
    from torchrl_wbrm.algos import algo_names

    return sorted(algo_names())


def build_cells(envs: list[str], algos: list[str], out: Path, quick: bool) -> list[dict]:
    """One cell per (env, algorithm); every cell of an env and seed shares one data collection (``data_cache``)."""
    cells = []
    for env in envs:
        extra = []
        if env == "mountain_car":  # the paper's 100 evaluation episodes (2 in the smoke version); 5 at training time
            extra = [f"eval.episodes={2 if quick else 100}", f"eval.train_episodes={1 if quick else 5}"]
        for algo in algos:
            cells.append({"env": env, "method": algo, "overrides": [
                f"env={env}", f"algo={algo}", "logger=none", "plots=false", "checkpoint_every=0",
                f"data_cache={out / 'data_cache'}", *extra]})
    return cells


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
    parser.add_argument("--algos", nargs="+", default=None, help=f"default: every registered algo ({available_algos()})")
    parser.add_argument("--envs", nargs="+", default=["lqr_exp1", "lqr_exp2", "lqr_exp3", "mountain_car"])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--jobs", type=int, default=2, help="parallel local runs")
    parser.add_argument("--launcher", default=None,
                        help="a Hydra launcher instead of local processes: submitit_local, submitit_slurm, ray "
                             "(pip install -e '.[sweeps]')")
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
        raise SystemExit(f"Unknown algorithms {unknown}: choose from {available_algos()} (torchrl_wbrm/algos/).")
    if not args.report_only:
        from torchrl_wbrm.training.runs import TABLE_BUDGET, TABLE_QUICK_BUDGET, run_cells

        os.environ.setdefault("MPLBACKEND", "Agg")
        start = time.perf_counter()
        run_cells(build_cells(args.envs, algos, out, args.quick), range(1 if args.quick else args.seeds),
                  TABLE_QUICK_BUDGET if args.quick else TABLE_BUDGET, out, jobs=args.jobs, labels=LABELS,
                  launcher=args.launcher, launcher_args=args.launcher_args)
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
