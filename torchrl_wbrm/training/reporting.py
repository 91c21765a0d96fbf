"""Human-readable summaries of a run's results."""
from __future__ import annotations

__all__ = ["ci_cell", "load_results", "results_table", "summarise"]


def summarise(results: dict) -> str:
    """A few lines: the final evaluation against the exact optimum (LQR) or the mean return (MountainCar)."""
    f = results.get("final", {})
    w = results.get("weights", {})
    algo = results.get("algo", "wbrm")
    detail = f"ratio source: {results['ratio']['source']}" if algo in ("wbrm", "brm") else "baseline"
    lines = [f"env {results['env']}  seed {results['seed']}  algo {algo} ({detail})"]
    if "regret" in f:
        lines += [
            f"return        {f['return']:.4f} ± {f['return_ci']:.4f}   (exact optimum {f['optimal_return_exact']:.4f})",
            f"paired regret {f['regret']:.4f} ± {f['regret_ci']:.4f}",
        ]
        if "q_error_expert" in f:  # methods without a Q network (bc) have none
            lines.append(
                f"Q̂ error / spread of Q*: expert {100 * f['q_error_expert']:.1f}%  behaviour {100 * f['q_error_behaviour']:.1f}%"
                f"   bias on expert {f['q_bias_expert']:+.3f}"
            )
    elif "return" in f:
        lines.append(f"return {f['return']:.2f} ± {f['return_ci']:.2f} over the evaluation episodes")
    if w:
        lines.append(
            f"weights over D: mean {w['mean_behaviour']:.3f}  ESS {w['ess']:.0f} ({100 * w['ess_fraction']:.2f}%)  max {w['max']:.3g}"
        )
    r = results.get("ratio", {})
    if "ratio_relative_l2" in r:
        lines.append(
            f"ŵ vs true ratio: relative L2 error {r['ratio_relative_l2']:.3f}  behaviour mean {r['ratio_mean_behaviour']:.3f}"
        )
    if "wall_seconds" in results:
        lines.append(f"wall time {results['wall_seconds']:.1f} s (data {results.get('data_seconds', 0):.1f} s)")
    return "\n".join(lines)


def load_results(root) -> list[dict]:
    """Every ``results.json`` under ``root`` (a Hydra multirun directory, or any tree of run directories)."""
    import json
    from pathlib import Path

    records = []
    for path in sorted(Path(root).rglob("results.json")):
        records.append(json.loads(path.read_text()))
    if not records:
        raise FileNotFoundError(f"No results.json under {root}: did the runs finish?")
    return records


def _lookup(record: dict, dotted: str):
    node = record
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


def ci_cell(records: list[dict], path: str, digits: int = 4) -> str:
    """``mean ± 95% CI`` of the number at dotted ``path`` over ``records`` (the value alone for one record, "–" for
    none): one cell of a results table."""
    from torchrl_wbrm.evaluation.stats import mean_ci

    values = [float(v) for v in (_lookup(r, path) for r in records) if isinstance(v, (int, float))]
    if not values:
        return "–"
    if len(values) == 1:
        return f"{values[0]:.{digits}f}"
    ci = mean_ci(values)
    return f"{ci.mean:.{digits}f} ± {ci.half_width:.{digits}f}"


def results_table(records: list[dict], group_by: list[str], metrics: dict[str, str], *, digits: int = 4) -> str:
    """A Markdown table: one row per distinct value of ``group_by`` (config paths), ``mean ± 95% CI`` over seeds.

    ``metrics`` maps a column title to a dotted path in the results (e.g. ``{"regret": "final.regret"}``). The CI is
    Student-t over the runs of a row (the seeds), so it states how much the figure moves from seed to seed.
    """
    rows: dict[tuple, list[dict]] = {}
    for rec in records:
        key = tuple(_lookup(rec, "config." + g) if not g.startswith("=") else _lookup(rec, g[1:]) for g in group_by)
        rows.setdefault(key, []).append(rec)
    header = [g.lstrip("=") for g in group_by] + ["seeds"] + list(metrics)
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for key in sorted(rows, key=lambda k: tuple(str(x) for x in k)):
        recs = rows[key]
        cells = [str(k) for k in key] + [str(len(recs))]
        cells += [ci_cell(recs, path, digits) for path in metrics.values()]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
