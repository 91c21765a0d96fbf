"""Does weighting the Bellman residual by the density ratio help? The study, against the exact LQR optimum.

    python recipes/weighting_study.py              # the full study (about an hour on 2 cores)
    python recipes/weighting_study.py --quick      # a smoke version (seconds; CI runs it)
    python recipes/weighting_study.py --blocks regimes   # one block (weighting, regimes, mountain_car)
    python recipes/weighting_study.py --blocks regimes --regimes "behaviour start wide (x₀ ~ N(0, 3² I))"
    python recipes/weighting_study.py ... --first-seed 10 --seeds 10 --out <new>   # fresh seeds 10-19

Each cell is a set of overrides of ``configs/wbrm_offline.yaml`` run for several seeds (its seeds together in one
process, the cells in parallel processes, one torch thread each). Cells already finished (their results.json exists)
are skipped, so an interrupted study resumes. Outputs in ``--out``: one run directory per cell and seed, ``tables.md``
(mean ± 95% CI over seeds) and ``weighting_study.png``.

Blocks:
- ``weighting`` (LQR exp1-3): unweighted vs the paper's learned ratio vs the true ratio, the ratio stabilisers
  (bound Ψ, the relative ratio), weight shaping (tempering, clipping, a floor by mixing), behaviour cloning on top,
  and behaviour cloning of the expert alone as a reference row;
  The full grid runs on exp1; exp2 and exp3 run the main contrasts;
- ``regimes`` (LQR exp1): where the expert's data should carry information the behaviour data lacks: a noisier or
  poorer expert, a behaviour policy far from the expert (no feedback gain, twice the noise), and a small Q network
  on little behaviour data (where focusing the fit on the expert's region should matter most), and a shifted start
  distribution (the behaviour episodes start from N(0, 3² I) or N(0, 0.3² I), the expert's and the scored ones
  from the system's N(0, I)); ``--regimes`` runs some of them;
- ``mountain_car``: unweighted vs the learned ratio on the paper's data sizes.

Defaults are chosen without the ground truth: among the learned-ratio configurations, the one with the lowest
held-out Bellman residual on unseen behaviour episodes (``select`` in tables.md); the exact optimum only scores.
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

#: Every weighted level states its whole shaping (temper, clip, mix), so that its label holds whatever the recipe's
#: defaults are: the recipe's default is ŵ^0.25, and a level that set only ``ratio.source`` would inherit it.
RAW = ["ratio.temper=1.0", "ratio.clip=null", "ratio.mix=0.0"]
WEIGHTING = {
    "unweighted": ["ratio.source=none"],
    "learned ŵ (paper)": ["ratio.source=learned", *RAW],
    "exact w": ["ratio.source=exact", *RAW],
    "learned ŵ, Ψ=20": ["ratio.source=learned", *RAW, "ratio.bounds=[0.001,20.0]"],
    "learned relative ŵ, β=½": ["ratio.source=learned", *RAW, "ratio.relative_beta=0.5"],
    "learned ŵ^0.25 (the recipe's default)": ["ratio.source=learned", "ratio.temper=0.25", "ratio.clip=null",
                                              "ratio.mix=0.0"],
    "learned min(ŵ, 10)": ["ratio.source=learned", *RAW, "ratio.clip=10.0"],
    "learned ½ + ½ŵ": ["ratio.source=learned", *RAW, "ratio.mix=0.5"],
    "exact ½ + ½w": ["ratio.source=exact", *RAW, "ratio.mix=0.5"],
    "unweighted + BC": ["ratio.source=none", "q.bc_alpha=2.5"],
    "learned ŵ + BC": ["ratio.source=learned", *RAW, "q.bc_alpha=2.5"],
    "BC of the expert alone": ["algo=bc"],
}
#: exp2 and exp3 run the main contrasts only (the full grid on exp1), to fit the study in about an hour here
OTHER_ENV_METHODS = ["unweighted", "learned ŵ (paper)", "exact w", "learned ŵ^0.25 (the recipe's default)",
                     "learned ½ + ½ŵ", "learned ŵ + BC", "BC of the expert alone"]
REGIME_METHODS = ["unweighted", "learned ŵ (paper)", "exact w", "learned ½ + ½ŵ",
                  "learned ŵ^0.25 (the recipe's default)"]
REGIMES = {
    "expert τ=0.2": ["env.lqr_data.expert_tau=0.2"],
    "expert τ=0.5 (poor)": ["env.lqr_data.expert_tau=0.5"],
    "behaviour far (gain 0, noise 1)": ["env.lqr_data.behaviour_gain_scale=0.0", "env.lqr_data.behaviour_noise_std=1.0"],
    "small Q (1×16) + little data (200 episodes)": ["q.num_cells=[16]", "env.lqr_data.behaviour_episodes=200"],
    # a shifted start distribution: the behaviour episodes start from N(0, s² I), the expert's and the scored
    # episodes from the system's N(0, I); the exact ratio and the behaviour samples Q̂ is scored on follow the shift
    "behaviour start wide (x₀ ~ N(0, 3² I))": ["env.lqr_data.behaviour_initial_std=3.0"],
    "behaviour start narrow (x₀ ~ N(0, 0.3² I))": ["env.lqr_data.behaviour_initial_std=0.3"],
}
MOUNTAIN_CAR = {
    "unweighted": ["ratio.source=none"],
    "learned ŵ (paper)": WEIGHTING["learned ŵ (paper)"],
    "learned ŵ^0.25 (the recipe's default)": WEIGHTING["learned ŵ^0.25 (the recipe's default)"],
}


BLOCKS = ("weighting", "regimes", "mountain_car")


def build_cells(quick: bool, blocks=BLOCKS, regimes=None, methods=None) -> list[dict]:
    """The study's cells, block by block (``blocks``: any of :data:`BLOCKS`; ``quick`` runs the weighting block's
    smoke version only; ``regimes``: the regimes block's settings to run, default all of :data:`REGIMES`;
    ``methods``: its methods, default all of :data:`REGIME_METHODS`, e.g. two of them for more seeds)."""
    unknown = sorted(set(blocks) - set(BLOCKS))
    if unknown:
        raise ValueError(f"weighting_study blocks: unknown {unknown}; choose from {list(BLOCKS)}")
    regimes = list(REGIMES) if regimes is None else list(regimes)
    unknown = sorted(set(regimes) - set(REGIMES))
    if unknown:
        raise ValueError(f"weighting_study regimes: unknown {unknown}; choose from {list(REGIMES)}")
    regime_methods = list(REGIME_METHODS) if methods is None else list(methods)
    unknown = sorted(set(regime_methods) - set(REGIME_METHODS))
    if unknown:
        raise ValueError(f"weighting_study regime methods: unknown {unknown}; choose from {REGIME_METHODS}")
    cells = []
    envs = ["lqr_exp1"] if quick else ["lqr_exp1", "lqr_exp2", "lqr_exp3"]
    methods = ["unweighted", "learned ŵ (paper)", "learned ½ + ½ŵ"] if quick else list(WEIGHTING)
    for env in envs if "weighting" in blocks else ():
        for method in methods if (quick or env == "lqr_exp1") else OTHER_ENV_METHODS:
            cells.append({"block": "weighting", "env": env, "setting": "paper data", "method": method,
                          "overrides": [f"env={env}", *WEIGHTING[method]]})
    if not quick and "regimes" in blocks:
        for regime in regimes:
            extra = REGIMES[regime]
            for method in regime_methods:
                cells.append({"block": "regimes", "env": "lqr_exp1", "setting": regime, "method": method,
                              "overrides": ["env=lqr_exp1", *extra, *WEIGHTING[method]]})
    if not quick and "mountain_car" in blocks:
        for method, extra in MOUNTAIN_CAR.items():
            cells.append({"block": "mountain_car", "env": "mountain_car", "setting": "paper data", "method": method,
                          "overrides": ["env=mountain_car", "eval.train_episodes=5", "eval.episodes=100", *extra]})
    return cells


def tables(out: Path) -> str:
    from torchrl_wbrm.training.reporting import load_results, results_table

    records = load_results(out)
    lqr = {
        "paired regret": "final.regret",
        "Q̂ error / spread (expert)": "final.q_error_expert",
        "Q̂ bias (expert)": "final.q_bias_expert",
        "ESS of weights (of ~18k)": "weights.ess",
        "held-out Bellman residual": "final.held_out_bellman_residual",
    }
    parts = []
    for block, title in (("weighting", "Weighting on the paper's data"), ("regimes", "Regimes (LQR exp1)"),
                         ("mountain_car", "MountainCarContinuous-v0")):
        recs = [r for r in records if r.get("study", {}).get("block") == block]
        if not recs:
            continue
        metrics = lqr if block != "mountain_car" else {"return (100 episodes)": "final.return",
                                                       "ESS of weights": "weights.ess"}
        parts.append(f"### {title}\n\n" + results_table(recs, ["=study.env", "=study.setting", "=study.method"], metrics))
    paired = paired_table(records)
    if paired:
        parts.append("### Against the unweighted residual, paired over seeds (LQR)\n\n" + paired)
    parts.append("### select: the lowest held-out Bellman residual among learned-ratio configurations\n\n" + select(records))
    return "\n\n".join(parts)


#: the figures :func:`paired_table` compares (lower is better for both)
PAIRED = {"paired regret": "regret", "Q̂ error / spread (expert)": "q_error_expert"}


def paired_table(records: list[dict]) -> str:
    """Each weighted method against ``unweighted`` in the same (block, env, setting), on the LQR figures: the mean of
    the per-seed differences (method − unweighted) with its 95% Student-t interval over the seeds both ran (the same
    data and initialisation for a seed), and whether the interval lies below 0 (``better``), above (``worse``) or
    holds 0 (``tie``). Pairing removes the seed-to-seed spread both share, which the per-method intervals above keep:
    this is the table that says whether weighting pays. Empty without LQR runs of ``unweighted``."""
    from torchrl_wbrm.evaluation import mean_ci
    from torchrl_wbrm.training.reporting import split_by_status

    groups: dict[tuple, dict[str, dict[int, dict]]] = {}
    for r in split_by_status(records)[0]:
        s = r.get("study", {})
        if "regret" not in (r.get("final") or {}):  # LQR runs only (MountainCar has no regret)
            continue
        groups.setdefault((s.get("block"), s.get("env"), s.get("setting")), {}).setdefault(s.get("method"), {})[
            r["seed"]] = r["final"]
    lines = ["| block | env | setting | method | seeds | " + " | ".join(f"{t}: method − unweighted [95% CI]"
                                                                        for t in PAIRED) + " |",
             "|" + "---|" * (5 + len(PAIRED))]
    for (block, env, setting), methods in sorted(groups.items(), key=lambda kv: tuple(map(str, kv[0]))):
        base = methods.get("unweighted")
        if not base:
            continue
        for method, finals in sorted(methods.items()):
            seeds = sorted(set(finals) & set(base))
            if method == "unweighted" or len(seeds) < 2:
                continue
            cells = []
            for key in PAIRED.values():
                ci = mean_ci([finals[k][key] - base[k][key] for k in seeds])
                verdict = "better" if ci.high < 0 else ("worse" if ci.low > 0 else "tie")
                cells.append(f"{ci.mean:+.4f} [{ci.low:+.4f}, {ci.high:+.4f}] {verdict}")
            lines.append(f"| {block} | {env} | {setting} | {method} | {len(seeds)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) if len(lines) > 2 else ""


def select(records: list[dict]) -> str:
    """Per env, the learned-ratio method with the lowest mean held-out Bellman residual (no ground truth used)."""
    import numpy as np

    lines = ["| env | selected | its held-out residual | its paired regret | unweighted regret |", "|---|---|---|---|---|"]
    by_env: dict = {}
    for r in records:
        s = r.get("study", {})
        if s.get("block") != "weighting" or s.get("env") == "mountain_car":
            continue
        by_env.setdefault(s["env"], {}).setdefault(s["method"], []).append(r)
    for env, methods in sorted(by_env.items()):
        def mean(method, key):
            return float(np.mean([r["final"][key] for r in methods[method]]))

        learned = [m for m in methods if m.startswith("learned")]
        if not learned:
            continue
        best = min(learned, key=lambda m: mean(m, "held_out_bellman_residual"))
        unweighted = f"{mean('unweighted', 'regret'):.4f}" if "unweighted" in methods else "–"
        lines.append(f"| {env} | {best} | {mean(best, 'held_out_bellman_residual'):.5f} | {mean(best, 'regret'):.4f} | {unweighted} |")
    return "\n".join(lines)


def plot(out: Path) -> Path | None:
    """``weighting_study.png``: the weighting block's paired regret per env and method (mean ± 95% CI); None when
    that block has no runs (``--blocks regimes`` or ``mountain_car`` alone)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchrl_wbrm.training.plots import plot_ci_rows, save_figure
    from torchrl_wbrm.training.reporting import load_results

    records = [r for r in load_results(out) if r.get("study", {}).get("block") == "weighting"]
    envs = sorted({r["study"]["env"] for r in records})
    if not envs:
        return None
    fig, axes = plt.subplots(1, len(envs), figsize=(5 * len(envs), 4.5), sharey=True, squeeze=False)
    methods = list(dict.fromkeys(r["study"]["method"] for r in records))
    for ax, env in zip(axes[0], envs):
        rows = {m: [r["final"]["regret"] for r in records if r["study"]["env"] == env and r["study"]["method"] == m]
                for m in methods}
        plot_ci_rows(ax, rows, log=True)
        ax.set_title(f"{env}: paired regret (mean ± 95% CI)")
        ax.axvline(0.01, color="grey", ls=":", label="goal 0.01")
        ax.legend(fontsize=8)
    return save_figure(fig, out / "weighting_study.png")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="tiny budgets, exp1, 3 methods, 1 seed")
    parser.add_argument("--seeds", type=int, default=3, help="how many seeds (default 3; --quick: 1)")
    parser.add_argument("--first-seed", type=int, default=0,
                        help="the first seed (default 0): fresh seeds to confirm a finding, e.g. --first-seed 10 "
                             "--seeds 10 runs seeds 10-19 (into an --out of their own, since the tables read "
                             "every run there)")
    parser.add_argument("--blocks", nargs="+", default=list(BLOCKS), choices=BLOCKS, help="the blocks to run")
    parser.add_argument("--regimes", nargs="+", default=None, metavar="REGIME",
                        help=f"the regimes block's settings to run (default all: {list(REGIMES)})")
    parser.add_argument("--methods", nargs="+", default=None, metavar="METHOD",
                        help=f"the regimes block's methods to run (default all: {REGIME_METHODS})")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--out", default=None,
                        help="where the runs and tables go (default results/weighting_study; --quick: results/weighting_study_quick)")
    from studies.docs_fragments import add_docs_dir_argument, docs_dir_from_args, publish_study

    add_docs_dir_argument(parser)
    args = parser.parse_args()
    os.environ.setdefault("MPLBACKEND", "Agg")
    out = Path(args.out or ("results/weighting_study_quick" if args.quick else "results/weighting_study"))  # a smoke run never mixes with the full one
    try:
        cells = build_cells(args.quick, args.blocks, args.regimes, args.methods)
    except ValueError as error:
        parser.error(str(error))
    if args.first_seed < 0 or args.seeds < 1:
        parser.error(f"--first-seed must be >= 0 and --seeds >= 1, got --first-seed {args.first_seed} "
                     f"--seeds {args.seeds}")
    seeds = range(args.first_seed, args.first_seed + (1 if args.quick else args.seeds))
    from studies.runs import run_cells, study_budget

    budget = study_budget("quick" if args.quick else "weighting")

    run_cells(cells, seeds, budget, out, jobs=args.jobs)
    text = tables(out)
    (out / "tables.md").write_text(text + "\n")
    figure = plot(out)
    print(text)
    publish_study("weighting_study", out / "tables.md", docs_dir_from_args(args.docs_dir, args.quick), seeds=seeds,
                  budget="quick" if args.quick else "weighting", budget_overrides=budget, figures=[figure])
    from torchrl_wbrm.training.logging import log_study_summary  # the group's wandb summary run (offline)

    log_study_summary("weighting_study", out, tables=[out / "tables.md"], figures=[figure] if figure else [])


if __name__ == "__main__":
    main()
