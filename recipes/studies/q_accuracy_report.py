"""The Q* accuracy study's report: ``tables.md`` and ``q_accuracy_study.png``, read from the finished runs of
``recipes/q_accuracy_study.py`` (which runs them and calls :func:`report`), and the study's levels that the report
names. Nothing here trains.

``tables.md``: the factor search's base on every system, each block's levels against it, the selection by the
held-out Bellman residual (:func:`select`, :func:`adopt`: no ground truth), the recipe as it is now beside its
unweighted comparator, every level on every system (paired regret, Q̂ error) and the MountainCar block.
"""
from __future__ import annotations

from pathlib import Path

SYSTEMS = ["lqr_exp1", "lqr_exp2", "lqr_exp3", "lqr_nondiag", "lqr_large_f"]
DEFAULT = "default"
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
#: The recipe as it is now (no overrides: GELU Q) and its unweighted comparator, 5 seeds on every
#: system: the figures the goals are judged on.
ADOPTED = {
    "the recipe's default now": [],
    "unweighted": ["ratio.source=none"],
}

def is_default(level: str) -> bool:
    return level.endswith("(default)")

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
    default_level = next(level for level in BLOCKS[block] if is_default(level))
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
    default_level = next(level for level in BLOCKS[block] if is_default(level))
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
    if is_default(chosen):
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
            if recs and not is_default(level):
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


#: the figures of every LQR table: column -> dotted path in a run's results
METRICS = {"paired regret": "final.regret", "Q̂ error / spread (expert)": "final.q_error_expert",
           "Q̂ bias (expert)": "final.q_bias_expert", "held-out Bellman residual": "final.held_out_bellman_residual"}


def tables(out: Path) -> str:
    from torchrl_wbrm.training.reporting import results_table

    records, metrics = _records(out), METRICS
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


def report(out: Path) -> tuple[str, Path | None]:
    """Write ``tables.md`` and ``q_accuracy_study.png`` into ``out`` from its finished runs; returns the text and the
    figure (``None`` when no block ran)."""
    text = tables(out)
    (Path(out) / "tables.md").write_text(text + "\n")
    return text, plot(out)
