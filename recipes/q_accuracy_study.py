"""How accurately does the recipe estimate Q*? Its network and optimisation settings, against the exact LQR optimum.

    python recipes/q_accuracy_study.py                   # LQR: 5 systems, every factor, 3 seeds (5 for the default)
    python recipes/q_accuracy_study.py --blocks mountain_car   # MountainCar: default vs TD3+BC, 5 seeds
    python recipes/q_accuracy_study.py --quick           # a smoke version (seconds; CI runs it)

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
``q_accuracy_study.png``.
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

SYSTEMS = ["lqr_exp1", "lqr_exp2", "lqr_exp3", "lqr_nondiag", "lqr_large_f"]
DEFAULT = "default"
#: The base the factor search ran around (SiLU Q): every factor cell starts from
#: it, so its cells stay the ones that ran whatever the recipe's defaults become. The rule adopted GELU (below), the
#: recipe's Q activation since; the "adopted" block runs the recipe as it is now.
BASE = ["q.activation=SiLU"]
#: block -> {level: overrides}; the recipe's default is the level named ``DEFAULT`` of every block (run once)
BLOCKS: dict[str, dict[str, list[str]]] = {
    "activation": {
        "ReLU": ["q.activation=ReLU"],
        "SiLU (default)": [],
        "ELU": ["q.activation=ELU"],
        "GELU": ["q.activation=GELU"],
        "Tanh": ["q.activation=Tanh"],
    },
    "weighting": {
        "learned ŵ^0.25 (default)": [],
        "learned ŵ": ["ratio.temper=1.0"],
        "learned ŵ^0.5": ["ratio.temper=0.5"],
        "learned ½ + ½ŵ": ["ratio.temper=1.0", "ratio.mix=0.5"],
        "learned min(ŵ, 10)": ["ratio.temper=1.0", "ratio.clip=10.0"],
        "unweighted": ["ratio.source=none"],
    },
    "ensemble": {
        "one network (default)": [],
        "two, mean": ["q.ensemble_size=2", "q.ensemble_reduction=mean"],
        "two, min": ["q.ensemble_size=2", "q.ensemble_reduction=min"],
    },
    "target rate": {
        "τ=0.01": ["q.target_tau=0.01"],
        "τ=0.05 (default)": [],
        "τ=0.2": ["q.target_tau=0.2"],
    },
    "step budget": {  # the cosine schedule anneals over q.steps, so each budget is its own run
        "1500": ["q.steps=1500"],
        "3000 (default)": [],
        "6000": ["q.steps=6000"],
    },
    "lr schedule": {
        "constant": ["q.lr_schedule=constant"],
        "cosine (default)": [],
    },
    "batch size": {
        "256 (default)": [],
        "512": ["q.batch_size=512"],
    },
    "combined": {  # every level the residual preferred in its own block (each within the noise), together
        "one factor at a time (default)": [],
        "GELU + two-network min + 6000 steps + ŵ^0.5": [
            "q.activation=GELU", "q.ensemble_size=2", "q.ensemble_reduction=min", "q.steps=6000", "ratio.temper=0.5"],
    },
    "target scaling": {
        "Q = MLP (default)": [],
        "Q = 10·MLP": ["q.value_scale=10.0"],
    },
}
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
#: The recipe as it is now (no overrides: GELU Q) and its unweighted comparator, 5 seeds on every
#: system: the figures the goals are judged on.
ADOPTED = {
    "the recipe's default now": [],
    "unweighted": ["ratio.source=none"],
}
#: the blocks besides :data:`BLOCKS` that ``--blocks`` takes
OTHER_BLOCKS = ("adopted", "mountain_car", DEFAULT)


def _is_default(level: str) -> bool:
    return level.endswith("(default)")


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
            if _is_default(level):
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


def _records(out: Path) -> list[dict]:
    """The study's results, each with its run's evaluation history under ``"_history"``."""
    import json

    records = []
    for path in sorted(Path(out).rglob("results.json")):
        record = json.loads(path.read_text())
        if "study" not in record:
            continue
        history = path.with_name("history.json")
        record["_history"] = json.loads(history.read_text()) if history.is_file() else []
        records.append(record)
    return records


def _block_records(records: list[dict], block: str) -> list[dict]:
    """The block's records, with the default's runs labelled as the block's default level: on the systems where the
    block ran another level, and on the seeds it ran there (paired: the defaults have 5 seeds, most levels 3)."""
    default_level = next(level for level in BLOCKS[block] if _is_default(level))
    rows = [r for r in records if r["study"]["block"] == block]
    seeds: dict[str, set] = {}
    for r in rows:
        seeds.setdefault(r["study"]["env"], set()).add(r["seed"])
    for r in records:
        s = r["study"]
        if s["block"] == DEFAULT and r["seed"] in seeds.get(s["env"], ()):
            rows.append({**r, "study": {**s, "block": block, "setting": block, "method": default_level}})
    order = list(BLOCKS[block])
    return sorted(rows, key=lambda r: (SYSTEMS.index(r["study"]["env"]) if r["study"]["env"] in SYSTEMS else 99,
                                       order.index(r["study"]["method"]) if r["study"]["method"] in order else 99))


def select(records: list[dict], block: str) -> tuple[str, dict, dict]:
    """The level of ``block`` with the lowest held-out Bellman residual, and whether it is lower beyond the noise.

    Per system, a level's mean residual over its seeds is divided by the default's mean over the same seeds
    (paired); the score is the geometric mean over the systems where the level ran. The noise: the paired log-ratios
    log(residual / default's residual), one per system and seed, give a mean with a 95% Student-t interval; a level
    is *better beyond the noise* when the whole interval is below 0. Returns ``(best level, scores, intervals)``,
    ``intervals[level] = (mean, half width)`` of the paired log-ratio. No ground truth is used.
    """
    import numpy as np

    from torchrl_wbrm.evaluation.stats import mean_ci

    residual: dict[str, dict[str, dict[int, float]]] = {}  # level -> env -> seed -> held-out residual
    for r in _block_records(records, block):
        residual.setdefault(r["study"]["method"], {}).setdefault(r["study"]["env"], {})[r["seed"]] = (
            r["final"]["held_out_bellman_residual"])
    default_level = next(level for level in BLOCKS[block] if _is_default(level))
    base = residual.get(default_level, {})
    scores, intervals = {}, {}
    for level, envs in residual.items():
        if block == "weighting" and not level.startswith("learned"):
            continue
        paired = {env: by_seed for env, by_seed in envs.items()
                  if env in base and all(seed in base[env] for seed in by_seed)}
        if not paired:
            continue
        ratios = [np.mean(list(by_seed.values())) / np.mean([base[env][seed] for seed in by_seed])
                  for env, by_seed in paired.items()]
        scores[level] = float(np.exp(np.mean(np.log(ratios))))
        logs = [float(np.log(v / base[env][seed])) for env, by_seed in paired.items() for seed, v in by_seed.items()]
        if level != default_level and len(logs) > 1:
            ci = mean_ci(logs)
            intervals[level] = (ci.mean, ci.half_width)
    return min(scores, key=scores.get), scores, intervals


def selection_verdict(chosen: str, intervals: dict) -> str:
    """The selection rule in words: a level is a candidate to replace the default only when its paired interval lies
    below 0 (:func:`adopt` takes one candidate per search)."""
    if _is_default(chosen):
        return f"{chosen}: keep"
    mean, half = intervals.get(chosen, (float("nan"), float("nan")))
    beyond = mean + half < 0
    verdict = "below the default beyond the noise" if beyond else "keep the default"
    return f"{chosen}: {verdict} (log-ratio {mean:+.3f} ± {half:.3f}" + (
        ")" if beyond else ", within the noise)")


def overview(records: list[dict], path: str, digits: int) -> str:
    """One row per level, one column per system: ``mean ± 95% CI`` over the level's seeds of the figure at dotted
    ``path``; the defaults first, over seeds 0-2 (the seeds of the 3-seed levels) and over all their seeds."""
    from torchrl_wbrm.training.reporting import ci_cell

    systems = [s for s in SYSTEMS if any(r["study"]["env"] == s for r in records)]
    defaults = [r for r in records if r["study"]["block"] == DEFAULT]
    if not systems or not defaults:
        return ""
    lines = ["| block | level | seeds | " + " | ".join(systems) + " |", "|---|---|---|" + "---|" * len(systems)]

    def row(block, level, recs):
        seeds = sorted({r["seed"] for r in recs})
        span = f"{seeds[0]}-{seeds[-1]}" if seeds == list(range(seeds[0], seeds[-1] + 1)) else ",".join(map(str, seeds))
        cells = [ci_cell([r for r in recs if r["study"]["env"] == env], path, digits) for env in systems]
        lines.append(f"| {block} | {level} | {span} | " + " | ".join(cells) + " |")

    row(DEFAULT, "the factor search's base (SiLU Q)", [r for r in defaults if r["seed"] < 3])
    row(DEFAULT, "the factor search's base (SiLU Q)", defaults)
    for level in ADOPTED:
        recs = [r for r in records if r["study"]["block"] == "adopted" and r["study"]["method"] == level]
        if recs:
            row("adopted", level, recs)
    for block, levels in BLOCKS.items():
        for level in levels:
            recs = [r for r in records if r["study"]["block"] == block and r["study"]["method"] == level]
            if recs and not _is_default(level):
                row(block, level, recs)
    return "\n".join(lines)


def adopt(records: list[dict]) -> tuple[str, str, list[str]] | None:
    """The factor search's one change to the defaults, by the held-out residual and the run time (no ground truth).

    The candidates are the levels :func:`select` finds lower than the default beyond the noise (their paired
    log-ratio interval below 0), across blocks. The one with the lowest score is adopted, unless other candidates'
    intervals overlap its own: then the cheapest of those (mean ``wall_seconds`` of its runs) is, since the residual
    cannot tell them apart. One change per search: the other levels were measured around the old default and are tried
    again around the new one. Returns ``(block, level, lines)`` (``lines``: each candidate in words), or ``None``.
    """
    import numpy as np

    candidates = []
    for block in BLOCKS:
        if not any(r["study"]["block"] == block for r in records):
            continue
        try:
            _, scores, intervals = select(records, block)
        except (KeyError, ValueError, StopIteration):
            continue
        for level, (mean, half) in intervals.items():
            if mean + half < 0:
                runs = [r["wall_seconds"] for r in records if r["study"]["block"] == block
                        and r["study"]["method"] == level and "wall_seconds" in r]
                candidates.append((scores[level], mean, half, float(np.mean(runs)) if runs else float("inf"),
                                   block, level))
    if not candidates:
        return None
    best = min(candidates)
    tied = [c for c in candidates if c[1] - c[2] <= best[1] + best[2]]  # intervals that overlap the best's
    chosen = min(tied, key=lambda c: c[3])
    lines = [f"{block}: {level} (score {score:.3f}, log-ratio {mean:+.3f} ± {half:.3f}, {wall:.0f} s a run)"
             for score, mean, half, wall, block, level in sorted(candidates)]
    return chosen[4], chosen[5], lines


def tables(out: Path) -> str:
    from torchrl_wbrm.training.reporting import results_table

    records = _records(out)
    metrics = {
        "paired regret": "final.regret",
        "Q̂ error / spread (expert)": "final.q_error_expert",
        "Q̂ bias (expert)": "final.q_bias_expert",
        "held-out Bellman residual": "final.held_out_bellman_residual",
    }
    parts = []
    defaults = [r for r in records if r["study"]["block"] == DEFAULT]
    if defaults:
        parts.append("### The factor search's base (SiLU Q; 5 seeds)\n\n" + results_table(
            sorted(defaults, key=lambda r: SYSTEMS.index(r["study"]["env"])), ["=study.env"],
            {**metrics, "exact optimum": "final.optimal_return_exact", "return": "final.return"}))
    selections = ["| block | lowest held-out residual, and the rule's verdict | score of each level (geometric mean of "
                  "residual / default's) |", "|---|---|---|"]
    for block in BLOCKS:
        rows = _block_records(records, block)
        if not any(r["study"]["block"] == block for r in records):
            continue
        parts.append(f"### {block}\n\n" + results_table(rows, ["=study.env", "=study.method"], metrics))
        try:
            chosen, scores, intervals = select(records, block)
        except (KeyError, ValueError, StopIteration):
            continue
        scored = ", ".join(f"{k}: {v:.3f}" for k, v in sorted(scores.items(), key=lambda kv: kv[1]))
        selections.append(f"| {block} | {selection_verdict(chosen, intervals)} | {scored} |")
    parts.append("### Selection (no ground truth)\n\n" + "\n".join(selections))
    adopted = adopt(records)
    if adopted is not None:
        parts.append("### The factor search's change to the defaults\n\n" + "\n".join(f"- {line}" for line in adopted[2])
                     + f"\n\nAdopted: **{adopted[0]}: {adopted[1]}** (the lowest score, or the cheapest of the levels"
                       " whose intervals overlap the lowest's).")
    now = [r for r in records if r["study"]["block"] == "adopted"]
    if now:
        parts.append("### The recipe as it is now, and its unweighted comparator (5 seeds)\n\n" + results_table(
            sorted(now, key=lambda r: (SYSTEMS.index(r["study"]["env"]), r["study"]["method"])),
            ["=study.env", "=study.method"], {**metrics, "exact optimum": "final.optimal_return_exact"}))
    for title, path, digits in (("paired regret", "final.regret", 4), ("Q̂ error / spread of Q* (expert)",
                                                                         "final.q_error_expert", 3)):
        table = overview(records, path, digits)
        if table:
            parts.append(f"### Every level on every system: {title}\n\n" + table)
    mc = [r for r in records if r["study"]["block"] == "mountain_car"]
    if mc:
        parts.append("### MountainCarContinuous-v0 (100 episodes per seed)\n\n" + results_table(
            mc, ["=study.method"], {"return": "final.return", "wall s": "wall_seconds"}, digits=2))
    return "\n\n".join(parts)


def plot(out: Path) -> Path | None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchrl_wbrm.training.plots import plot_ci_rows, save_figure

    records = _records(out)
    blocks = [b for b in BLOCKS if any(r["study"]["block"] == b for r in records)]
    if not blocks:
        return None
    heights = [1.0 + 0.35 * len(BLOCKS[b]) for b in blocks]
    fig, axes = plt.subplots(len(blocks), 1, figsize=(9, sum(heights)), squeeze=False,
                             gridspec_kw={"height_ratios": heights})
    for ax, block in zip(axes[:, 0], blocks):
        rows = {}
        for r in _block_records(records, block):
            rows.setdefault(r["study"]["method"], []).append(r["final"]["regret"])
        plot_ci_rows(ax, rows, log=True)
        ax.axvline(0.01, color="grey", ls=":", label="goal 0.01")
        ax.set_title(f"{block}: paired regret, all systems pooled (mean ± 95% CI)", fontsize=9)
    return save_figure(fig, out / "q_accuracy_study.png", dpi=100)


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
    for seeds in sorted({1 if args.quick else c["seeds"] for c in cells}, reverse=True):  # the defaults first
        group = [c for c in cells if (1 if args.quick else c["seeds"]) == seeds]
        run_cells(group, range(seeds), budget, out, jobs=args.jobs)
    text = tables(out)
    (out / "tables.md").write_text(text + "\n")
    figure = plot(out)
    print(text)
    counts = sorted({1 if args.quick else c["seeds"] for c in cells}, reverse=True)
    publish_study("q_accuracy_study", out / "tables.md", docs_dir_from_args(args.docs_dir, args.quick),
                  seeds=" or ".join(f"{n} (0–{n - 1})" if n > 1 else "1 (0)" for n in counts) + " per cell",
                  budget="quick" if args.quick else "q_accuracy", budget_overrides=budget, figures=[figure])


if __name__ == "__main__":
    main()
