"""Convergence rates on LQR exp1: ŵ's error as the ratio sample size m grows, Q̂'s error as the data size n grows.

    python recipes/convergence_study.py            # about 15 minutes on 2 cores
    python recipes/convergence_study.py --quick    # smoke version
    python recipes/convergence_study.py --seeds 10 --ratio-sizes 1000 4000 16000 --q-sizes 2000 8000 32000

Lemma 4.1 of the paper bounds E‖ŵ − w‖²_{L2(P^b)} by O(m^{−2α/(d+2α)} log³m) for a ratio of Hölder smoothness α
in d = 4 dimensions (state 2 + action 2), so the L2 error falls like m^{−α/(d+2α)}: slope −1/6 for α = 1, −1/4 for
α = 2, → −1/2 as α → ∞ (the Gaussian ratio here is infinitely smooth). Theorem 4.1 gives the weighted excess risk
O(n^{−β/(d+2β)} log^{3/2} n) for Q* of smoothness β. We measure ‖ŵ − w‖ / ‖w‖ against the exact ratio and
RMS(Q̂ − Q*) / std(Q*) on expert samples against the exact Q* for the recipe's default weighting (learned ŵ^0.25;
the exact, sharply peaked ratio diverges at small n), fit log-log slopes (least squares over all seeds) with a
bootstrap 95% interval (:func:`bootstrap_slope`: the runs resampled with replacement within each size, 2,000 times,
numpy seed 0, so the report is reproducible) and draw them beside the theory's reference slopes; ``convergence.md``
and the figure's legend give each slope as ``slope [low, high]``. With 3 seeds per size the interval rests on few
distinct resamples and is narrower than a true 95% interval (percentile bootstraps under-cover with so few runs):
more ``--seeds`` make it firmer. The networks and step budgets are
fixed across sizes (the theorem lets the network grow with m and n), so an optimisation floor can flatten the
curves at large sizes.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

RATIO_SIZES = [1000, 2000, 4000, 8000, 16000, 32000]
Q_SIZES = [1000, 2000, 4000, 8000, 16000, 32000]
#: the run directory of a cell: <out>/<quantity>/<size>/seed<seed> (quantity: ratio or q)
LABELS = ("block", "size")


def build_cells(quick: bool, ratio_sizes: list[int] | None = None, q_sizes: list[int] | None = None) -> list[dict]:
    """One cell per (quantity, size): the ratio's error against m, Q̂'s error against n (``ratio_sizes`` and
    ``q_sizes`` default to :data:`RATIO_SIZES` and :data:`Q_SIZES`; ``quick`` keeps the first two of each)."""
    ratio_sizes = list(RATIO_SIZES if ratio_sizes is None else ratio_sizes)
    q_sizes = list(Q_SIZES if q_sizes is None else q_sizes)
    if quick:
        ratio_sizes, q_sizes = ratio_sizes[:2], q_sizes[:2]
    ratio_steps = "ratio.steps=30" if quick else "ratio.steps=2000"
    q_steps = "q.steps=30" if quick else "q.steps=3000"
    cells = []
    for m in ratio_sizes:  # m state-actions per side: m/20 expert episodes, 2m/20 behaviour (half to S^b)
        cells.append({"block": "ratio", "size": f"m{m}", "n": m, "overrides": [
            "env=lqr_exp1", f"env.lqr_data.expert_episodes={m // 20}", f"env.lqr_data.behaviour_episodes={2 * m // 20}",
            ratio_steps, "q.steps=1", "q.eval_every=1", "ratio.patience=10", "ratio.temper=1.0"]})
    for n in q_sizes:  # n transitions in D: behaviour episodes split half to S^b, 10% of D held out
        episodes = int(round(n / 20 / 0.5 / 0.9))
        cells.append({"block": "q", "size": f"n{n}", "n": n, "overrides": [
            "env=lqr_exp1", f"env.lqr_data.behaviour_episodes={episodes}", "ratio.source=learned", "ratio.temper=0.25",
            ratio_steps, q_steps, "q.eval_every=100000"]})
    return cells


def _slopes(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least-squares slopes of ``y`` on ``x`` along the last axis (one per row)."""
    x = x - x.mean(axis=-1, keepdims=True)
    return (x * (y - y.mean(axis=-1, keepdims=True))).sum(axis=-1) / (x * x).sum(axis=-1)


def fit_slope(sizes, errors) -> float:
    """Least-squares slope of log(error) on log(size), over every run (each seed a point)."""
    return float(_slopes(np.log(np.asarray(sizes, dtype=np.float64)), np.log(np.asarray(errors, dtype=np.float64))))


class SlopeCI(NamedTuple):
    """A fitted log-log slope with its bootstrap interval (``low``/``high`` nan with one run per size)."""

    slope: float
    low: float
    high: float
    resamples: int

    def format(self, digits: int = 3) -> str:
        if not np.isfinite(self.low):
            return f"{self.slope:.{digits}f} [n/a: one run per size]"
        return f"{self.slope:.{digits}f} [{self.low:.{digits}f}, {self.high:.{digits}f}]"


def bootstrap_slope(sizes, errors, *, resamples: int = 2000, seed: int = 0, level: float = 0.95) -> SlopeCI:
    """:func:`fit_slope` with a percentile bootstrap interval: ``resamples`` times, the runs of each size are
    resampled with replacement (each size keeps its number of runs, so every refit sees every size), the slope is
    refitted, and the interval is the (1 − level)/2 and (1 + level)/2 percentiles of the refits. ``seed`` fixes
    numpy's generator, so the same runs give the same interval."""
    sizes, errors = np.asarray(sizes, dtype=np.float64), np.asarray(errors, dtype=np.float64)
    groups = [np.flatnonzero(sizes == s) for s in np.unique(sizes)]
    if len(groups) < 2:
        raise ValueError(f"A slope needs at least two sizes, got {sorted(set(sizes.tolist()))}.")
    slope = fit_slope(sizes, errors)
    if all(len(g) == 1 for g in groups):
        return SlopeCI(slope, float("nan"), float("nan"), resamples)
    rng = np.random.default_rng(seed)
    idx = np.concatenate([g[rng.integers(0, len(g), size=(resamples, len(g)))] for g in groups], axis=1)
    refits = _slopes(np.log(sizes)[idx], np.log(errors)[idx])  # idx: [resamples, runs]
    low, high = np.percentile(refits, [50 * (1 - level), 50 * (1 + level)])
    return SlopeCI(slope, float(low), float(high), resamples)


def report(records: list[tuple[str, int, int, dict]], out: Path) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchrl_wbrm.training.plots import save_figure

    from torchrl_wbrm.evaluation import mean_ci

    panels = {
        "ratio": ("m (state-action samples per side)", lambda r: r["ratio"]["ratio_relative_l2"], "‖ŵ − w‖ / ‖w‖ (L2(P^b))",
                  {"α=1: −1/6": -1 / 6, "α=2: −1/4": -1 / 4, "α→∞: −1/2": -1 / 2}),
        "q": ("n (transitions in D)", lambda r: r["final"]["q_error_expert"], "RMS(Q̂ − Q*) / std(Q*) on expert samples",
              {"β=1: −1/6": -1 / 6, "β=2: −1/4": -1 / 4, "β→∞: −1/2": -1 / 2}),
    }
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    lines = ["| quantity | size | seeds | error (mean ± 95% CI) |", "|---|---|---|---|"]
    slopes: dict[str, SlopeCI] = {}
    for ax, (kind, (xlabel, get, ylabel, refs)) in zip(axes, panels.items()):
        recs = [(size, get(r)) for k, size, _, r in records if k == kind]
        if not recs:
            continue
        sizes = sorted({s for s, _ in recs})
        means, halfs = [], []
        for s in sizes:
            ci = mean_ci([e for size, e in recs if size == s])
            means.append(ci.mean)
            halfs.append(0.0 if ci.n < 2 else ci.half_width)
            lines.append(f"| {kind} | {s} | {ci.n} | {ci.mean:.4f} ± {halfs[-1]:.4f} |")
        slope = slopes[kind] = bootstrap_slope([s for s, _ in recs], [e for _, e in recs])
        ax.errorbar(sizes, means, yerr=halfs, marker="o", capsize=3,
                    label=f"measured, slope {slope.format(2)} (95% bootstrap)")
        for label, ref in refs.items():
            ax.plot(sizes, [means[0] * (s / sizes[0]) ** ref for s in sizes], ls=":", label=label)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.legend(fontsize=8)
    save_figure(fig, out / "convergence.png")
    slope_lines = ["| quantity | fitted log-log slope [95% bootstrap CI] | theory's reference slopes |", "|---|---|---|"]
    for kind, slope in slopes.items():
        refs = ", ".join(panels[kind][3])
        slope_lines.append(f"| {kind} | {slope.format()} | {refs} |")
    resamples = next(iter(slopes.values())).resamples if slopes else 0
    text = ("\n".join(lines) + "\n\nFitted log-log slopes: " + ", ".join(f"{k}: {v.format()}" for k, v in slopes.items())
            + "\n\n" + "\n".join(slope_lines)
            + f"\n\nLeast squares over every run; the interval: {resamples} bootstrap resamples of the runs within each "
              "size, refitted, 2.5 and 97.5 percentiles (numpy seed 0).")
    (out / "convergence.md").write_text(text + "\n")
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--ratio-sizes", nargs="+", type=int, default=None, help=f"m values (default {RATIO_SIZES})")
    parser.add_argument("--q-sizes", nargs="+", type=int, default=None, help=f"n values (default {Q_SIZES})")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--out", default=None,
                        help="where the runs and tables go (default results/convergence_study; --quick: results/convergence_study_quick)")
    from studies.docs_fragments import add_docs_dir_argument, docs_dir_from_args, publish_study

    add_docs_dir_argument(parser)
    args = parser.parse_args()
    os.environ.setdefault("MPLBACKEND", "Agg")
    out = Path(args.out or ("results/convergence_study_quick" if args.quick else "results/convergence_study"))  # a smoke run never mixes with the full one
    from studies.runs import cell_dir, run_cells, study_budget

    cells, seeds = build_cells(args.quick, args.ratio_sizes, args.q_sizes), range(1 if args.quick else args.seeds)
    budget = [*study_budget("convergence"), *(study_budget("convergence_quick") if args.quick else [])]
    run_cells(cells, seeds, budget, out, jobs=args.jobs, labels=LABELS)
    records = [(cell["block"], cell["n"], seed,
                json.loads((cell_dir(out, cell, seed, labels=LABELS) / "results.json").read_text()))
               for cell in cells for seed in seeds]
    print(report(records, out))
    publish_study("convergence", out / "convergence.md", docs_dir_from_args(args.docs_dir, args.quick), seeds=seeds,
                  budget="convergence" + (" + convergence_quick" if args.quick else ""), budget_overrides=budget,
                  figures=[out / "convergence.png"], ci="a 95% Student-t interval over the seeds of a size; the "
                  "slopes: a 95% bootstrap percentile interval")
    from torchrl_wbrm.training.logging import log_study_summary  # the group's wandb summary run (offline)

    log_study_summary("convergence_study", out, tables=[out / "convergence.md"], figures=[out / "convergence.png"])


if __name__ == "__main__":
    main()
