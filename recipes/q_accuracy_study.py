"""How accurately does the recipe estimate Q*? Its network and optimisation settings, against the exact LQR optimum.

    python recipes/q_accuracy_study.py                   # LQR: 5 systems, every factor, 3 seeds (5 for the default)
    python recipes/q_accuracy_study.py --blocks mountain_car   # MountainCar: default vs TD3+BC, 5 seeds
    python recipes/q_accuracy_study.py --quick           # a smoke version (seconds; CI runs it)
    python recipes/q_accuracy_study.py --report-only     # rebuild tables.md and the figure from finished runs

Every cell is a set of overrides of ``configs/wbrm_offline.yaml`` on top of the recipe's defaults (the weighted
method, learned ŵ and its shaping), one factor changed at a time, run for several seeds (a cell's seeds together in
one process, the cells in parallel processes, one torch thread each). Finished cells (their results.json exists) are
skipped, so an interrupted study resumes.

Systems: the paper's LQR exp1-3 and two not in the paper: ``lqr_nondiag`` (coupled F, G and R) and ``lqr_large_f``
(F = 0.9 I). Factors: Q's hidden activation (ReLU, SiLU, ELU, GELU, Tanh), the target rate τ, the batch size, a
learning-rate schedule (cosine, the default, or constant), the step budget (1500, 3000 or 6000 steps, each its own
run: the cosine schedule anneals over the budget), a two-network ensemble (mean or min),
reward/target scaling (Q = s · MLP), and the weight shaping of ŵ (temper / mix / clip, unweighted beside them).
The combination of every level the criterion preferred runs on exp3 and large_f only (the systems where the default
misses the regret goal; it costs about three default runs).

Selection uses no ground truth: within each block, the level with the lowest held-out Bellman residual (unweighted
mean δ² on behaviour episodes held out of D), as a geometric mean over systems of its ratio to the default's on the
same seeds. It replaces the default only when it is lower beyond the noise: the 95% interval of the paired
log-ratios (one per system and seed) lies below 0. The weighting block selects among learned-ratio shapings only
(the unweighted residual favours w ≡ 1 by construction).
The exact optimum only scores: paired regret and Q̂ error relative to Q*'s spread on expert samples.

Outputs in ``--out``: one run directory per cell and seed, ``tables.md`` (mean ± 95% CI over seeds) and
``q_accuracy_study.png``, written by the report (``recipes/studies/q_accuracy_report.py``) from the finished runs.
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

from studies.q_accuracy_report import ADOPTED, BLOCKS, DEFAULT, SYSTEMS, is_default, report

#: The base the factor search ran around (SiLU Q): every factor cell starts from
#: it, so its cells stay the ones that ran whatever the recipe's defaults become. The rule adopted GELU (below), the
#: recipe's Q activation since; the "adopted" block runs the recipe as it is now.
BASE = ["q.activation=SiLU"]
#: levels run on every system in --systems; the other levels run on --factor-systems (all five by default)
EVERY_SYSTEM_LEVELS = {("activation", "ReLU"), ("weighting", "unweighted")}
#: levels run only on these systems (of those given): the combination of the preferred levels, the costliest cell (two
#: networks for 6,000 steps, ~3x a default run), on the two systems where the default misses the regret goal
LEVEL_SYSTEMS = {("combined", "GELU + two-network min + 6000 steps + ŵ^0.5"): ("lqr_exp3", "lqr_large_f")}
#: levels with as many seeds as the defaults: the unweighted residual is the default's comparator (its goal: the
#: weighted default no worse than the unweighted residual within the CI, over 5 seeds)
FIVE_SEED_LEVELS = {("weighting", "unweighted")}
#: the run order of the 3-seed cells, most informative first, so that an interrupted study has the headline cells:
#: the unweighted residual and ReLU on every system, the constant learning rate, a longer budget, an averaged
#: ensemble; the rest in block order
PRIORITY = [("weighting", "unweighted"), ("activation", "ReLU"), ("lr schedule", "constant"),
            ("step budget", "6000"), ("ensemble", "two, mean")]
MOUNTAIN_CAR = {  # env=mountain_car's defaults keep SiLU Q (configs/env/mountain_car.yaml); GELU beside it
    "wbrm (the recipe's default)": [],
    "td3bc, same budget": ["algo=td3bc"],
    "wbrm, GELU Q": ["q.activation=GELU"],
    "td3bc, same budget, GELU Q": ["algo=td3bc", "q.activation=GELU"],
}
#: the blocks besides :data:`BLOCKS` that ``--blocks`` takes
OTHER_BLOCKS = ("adopted", "mountain_car", DEFAULT)


def build_cells(quick: bool, blocks: list[str], systems=SYSTEMS, factor_systems=SYSTEMS) -> list[dict]:
    """Each cell once: the default and the unweighted residual (5 seeds) on every system, ReLU (3 seeds) on every
    system, each other level (3 seeds) on ``factor_systems`` (the levels of :data:`LEVEL_SYSTEMS` only on theirs)."""
    cells = []
    if quick:
        systems = factor_systems = ["lqr_exp1"]
    lqr_blocks = [b for b in blocks if b in BLOCKS]
    if quick:
        lqr_blocks = ["activation"]
    for env in systems if (lqr_blocks or DEFAULT in blocks) else ():
        cells.append({"block": DEFAULT, "env": env, "setting": DEFAULT, "method": DEFAULT,
                      "overrides": [f"env={env}", *BASE], "seeds": 5})
    for block in lqr_blocks:  # block by block, so that an interrupted study has whole blocks
        levels = BLOCKS[block]
        if quick:
            levels = {k: levels[k] for k in ("ReLU", "SiLU (default)")}
        for level, extra in levels.items():
            if is_default(level):
                continue
            envs = systems if (block, level) in EVERY_SYSTEM_LEVELS else factor_systems
            if (block, level) in LEVEL_SYSTEMS and not quick:
                envs = [env for env in envs if env in LEVEL_SYSTEMS[block, level]]
            for env in envs:
                cells.append({"block": block, "env": env, "setting": block, "method": level,
                              "overrides": [f"env={env}", *BASE, *extra],
                              "seeds": 5 if (block, level) in FIVE_SEED_LEVELS else 3})
    rank = {key: i for i, key in enumerate(PRIORITY)}
    cells.sort(key=lambda c: (c["block"] != DEFAULT, rank.get((c["block"], c["method"]), len(rank))))  # stable
    if "adopted" in blocks and not quick:
        for method, extra in ADOPTED.items():
            for env in systems:
                cells.append({"block": "adopted", "env": env, "setting": "adopted", "method": method,
                              "overrides": [f"env={env}", *extra], "seeds": 5})
    if "mountain_car" in blocks and not quick:
        for method, extra in MOUNTAIN_CAR.items():
            cells.append({"block": "mountain_car", "env": "mountain_car", "setting": "defaults", "method": method,
                          "overrides": ["env=mountain_car", *extra], "seeds": 5})
    return cells


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="tiny budgets, exp1, ReLU vs SiLU, 1 seed")
    parser.add_argument("--blocks", nargs="+", default=[*BLOCKS, "adopted"],
                        help=f"any of {[*BLOCKS, *OTHER_BLOCKS]} ({DEFAULT!r} alone: the factor search's "
                             "base only; 'adopted': the recipe as it is now and its unweighted comparator, 5 seeds)")
    parser.add_argument("--systems", nargs="+", default=SYSTEMS, help="systems of the defaults, ReLU and unweighted")
    parser.add_argument("--factor-systems", nargs="+", default=SYSTEMS,
                        help="systems of every other level (fewer: a cheaper study)")
    parser.add_argument("--default-seeds", type=int, default=5, help="seeds of the defaults' cells")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--out", default=None,
                        help="where the runs and tables go (default results/q_accuracy_study; --quick: results/q_accuracy_study_quick)")
    parser.add_argument("--report-only", action="store_true",
                        help="only rebuild tables.md and the figure from finished runs")
    from studies.docs_fragments import add_docs_dir_argument, docs_dir_from_args, publish_study

    add_docs_dir_argument(parser)
    args = parser.parse_args()
    unknown = [b for b in args.blocks if b not in BLOCKS and b not in OTHER_BLOCKS]
    if unknown:
        parser.error(f"--blocks: unknown {unknown}; choose from {[*BLOCKS, *OTHER_BLOCKS]}")
    os.environ.setdefault("MPLBACKEND", "Agg")
    out = Path(args.out or ("results/q_accuracy_study_quick" if args.quick else "results/q_accuracy_study"))  # a smoke run never mixes with the full one
    from studies.runs import run_cells, study_budget

    budget = study_budget("quick" if args.quick else "q_accuracy")

    cells = build_cells(args.quick, args.blocks, args.systems, args.factor_systems)
    for cell in cells:
        if cell["block"] == DEFAULT or (cell["block"], cell["method"]) in FIVE_SEED_LEVELS:
            cell["seeds"] = args.default_seeds
    for seeds in sorted({1 if args.quick else c["seeds"] for c in cells}, reverse=True) if not args.report_only else ():
        group = [c for c in cells if (1 if args.quick else c["seeds"]) == seeds]  # the defaults first
        run_cells(group, range(seeds), budget, out, jobs=args.jobs)
    text, figure = report(out)
    print(text)
    counts = sorted({1 if args.quick else c["seeds"] for c in cells}, reverse=True)
    publish_study("q_accuracy_study", out / "tables.md", docs_dir_from_args(args.docs_dir, args.quick),
                  seeds=" or ".join(f"{n} (0–{n - 1})" if n > 1 else "1 (0)" for n in counts) + " per cell",
                  budget="quick" if args.quick else "q_accuracy", budget_overrides=budget, figures=[figure])


if __name__ == "__main__":
    main()
