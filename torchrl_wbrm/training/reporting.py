"""Human-readable summaries of a run's results."""
from __future__ import annotations

import math

from torchrl_wbrm.keys import RESULTS

__all__ = ["below_behaviour", "ci_cell", "load_results", "per_seed_cell", "results_table", "return_fell",
           "split_by_status", "summarise"]


def _finite(value) -> bool:
    """A number (not a bool) that is finite: what a figure of results.json must be to be printed or compared."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _n(value, spec: str) -> str:
    """``format(value, spec)``, or ``"n/a"`` for a missing or non-finite figure (``null`` in results.json)."""
    return format(value, spec) if _finite(value) else "n/a"


def summarise(results: dict) -> str:
    """A few lines: the final evaluation against the exact optimum (LQR) or the mean return (MountainCar), and any
    flag (a diverged run, a Q̂ blow-up, a collapsed stage 1, a stage 1 worse than ŵ ≡ 1, a return that fell as
    training went on)."""
    f = results.get("final", {})
    w = results.get("weights", {})
    algo = results.get("algo", "wbrm")
    detail = f"ratio source: {results.get('ratio', {}).get('source')}" if algo in ("wbrm", "brm") else "baseline"
    lines = [f"env {results['env']}  seed {results['seed']}  algo {algo} ({detail})"]
    if results.get("status", "finished") != "finished":
        lines.append(f"STATUS {results['status'].upper()}: " + results.get("diverged", {}).get("message", ""))
    if "regret" in f:
        lines += [
            f"return        {_n(f['return'], '.4f')} ± {_n(f.get('return_ci'), '.4f')}   "
            f"(exact optimum {_n(f.get('optimal_return_exact'), '.4f')})",
            f"paired regret {_n(f['regret'], '.4f')} ± {_n(f.get('regret_ci'), '.4f')}",
        ]
        if "q_error_expert" in f:  # methods without a Q network (bc) have none
            qe, qb = f["q_error_expert"], f.get("q_error_behaviour")
            lines.append(
                f"Q̂ error / spread of Q*: expert {_n(None if qe is None else 100 * qe, '.1f')}%  "
                f"behaviour {_n(None if qb is None else 100 * qb, '.1f')}%   bias on expert {_n(f.get('q_bias_expert'), '+.3f')}"
            )
    elif "return" in f:
        lines.append(f"return {_n(f['return'], '.2f')} ± {_n(f.get('return_ci'), '.2f')} over the evaluation episodes")
        data = results.get("data", {})
        if "behaviour_mean_return" in data or "expert_mean_return" in data:  # the datasets' own, beside it
            lines.append(f"datasets' mean episode returns: behaviour {_n(data.get('behaviour_mean_return'), '.2f')}  "
                         f"expert {_n(data.get('expert_mean_return'), '.2f')}")
        if "normalised_score" in f:  # D4RL's score from the datasets' reference scores
            lines.append(f"normalised score {_n(f['normalised_score'], '.1f')} ± {_n(f.get('normalised_score_ci'), '.1f')}"
                         f"   (0: random actions, 100: the expert; behaviour data "
                         f"{_n(f.get('data_behaviour_normalised_score'), '.1f')})")
    if "offline_value" in f:  # FQE on D (eval.offline_value): the same return, estimated without the environment
        weighted = (f"   ŵ-weighted {_n(f['offline_value_weighted'], '.2f')} ± {_n(f.get('offline_value_weighted_ci'), '.2f')}"
                    if "offline_value_weighted" in f else "")
        lines.append(f"offline value (FQE on D, no environment) {_n(f['offline_value'], '.2f')} ± "
                     f"{_n(f.get('offline_value_ci'), '.2f')}{weighted}")
    if w:
        ess_fraction = w.get("ess_fraction")
        lines.append(
            f"weights over D: mean {_n(w.get('mean_behaviour'), '.3f')}  ESS {_n(w.get('ess'), '.0f')} "
            f"({_n(None if ess_fraction is None else 100 * ess_fraction, '.2f')}%)  max {_n(w.get('max'), '.3g')}"
        )
    r = results.get("ratio", {})
    if "ratio_relative_l2" in r:
        lines.append(
            f"ŵ vs true ratio: relative L2 error {_n(r['ratio_relative_l2'], '.3f')}  "
            f"behaviour mean {_n(r.get('ratio_mean_behaviour'), '.3f')}"
        )
    scale = results.get("q_scale") or {}
    if scale.get("blow_up"):
        lines.append(
            f"FLAG q_blow_up: |{scale['figure']}| = {_n(scale['max_abs_q_mean'], '.4g')} is more than "
            f"{_n(scale['factor'], 'g')} x r_max/(1 - gamma) = {_n(scale['bound'], '.4g')}: Q̂ has blown up."
        )
    check = results.get("ratio", {}).get("check") or {}
    if check.get("collapse"):
        lines.append(
            "FLAG ratio_collapse: stage 1 failed: " + "; ".join(check.get("reasons", [])) + " (ŵ at its lower bound "
            "on " + _n(100 * check.get("at_lower_bound", 0), ".0f") + "% of D). The weights carry no information; "
            "lower ratio.lr or check the data (ratio.source=none runs the unweighted method on purpose)."
        )
    if check.get("worse_than_uniform"):
        lines.append(
            f"FLAG ratio_worse_than_uniform: stage 1 {check.get('worse_than_uniform_reason')}. Lower ratio.lr or "
            "raise ratio.steps, or run ratio.source=none (the unweighted method)."
        )
    below = results.get("behaviour_check") or {}
    if below.get("below"):
        lines.append(
            f"FLAG below_behaviour: the policy's return {_n(below['return'], '.4g')} ± {_n(below['return_ci'], '.3g')} "
            f"is below the behaviour data's mean episode return {_n(below['behaviour_mean_return'], '.4g')}: "
            "the learned policy is worse than the data it learned from."
        )
    fell = results.get("return_check") or {}
    if fell.get("fell"):
        lines.append(
            f"FLAG return_fell: the final return {_n(fell['return'], '.4g')} ± {_n(fell['return_ci'], '.3g')} (step "
            f"{fell['step']}) is below the best evaluation's {_n(fell['best_return'], '.4g')} ± "
            f"{_n(fell['best_return_ci'], '.3g')} (step {fell['best_step']}), beyond both intervals, losing more than "
            f"{_n(100 * RETURN_FALL_FRACTION, '.0f')}% of its gain over the behaviour data: more steps made the "
            "policy worse. Check Q̂'s scale (q_mean in history.json) or shorten q.steps."
        )
    if "wall_seconds" in results:
        lines.append(f"wall time {_n(results['wall_seconds'], '.1f')} s (data {_n(results.get('data_seconds', 0), '.1f')} s)")
    return "\n".join(lines)


def below_behaviour(final: dict, data: dict) -> dict:
    """Whether the evaluated policy's mean return lies below the behaviour data's mean episode return (the
    ``below_behaviour`` flag): ``{"below": bool, "return", "return_ci", "behaviour_mean_return"}``; ``below`` is
    ``False`` when either figure is unknown (LQR is scored by its regret against the exact optimum instead)."""
    ret, ref = final.get("return"), data.get("behaviour_mean_return")
    out = {"below": False, "return": ret, "return_ci": final.get("return_ci"), "behaviour_mean_return": ref}
    if _finite(ret) and _finite(ref):
        out["below"] = bool(ret < ref)
    return out


#: ``return_fell`` needs the run to lose at least this fraction of its best evaluation's gain over the behaviour data
RETURN_FALL_FRACTION = 0.25


def return_fell(history: list[dict], data: dict) -> dict:
    """Whether stage 2's return fell as training went on (the ``return_fell`` flag). Both must hold:

    - the last evaluation's interval lies wholly below the best earlier evaluation's (``best − ci_best > last +
      ci_last``, each the 95% half-width over the evaluation episodes): disjoint intervals, rather than a test on the
      difference, keep the choice of the best of several evaluations from flagging noise;
    - the fall is at least :data:`RETURN_FALL_FRACTION` of the best evaluation's gain over the behaviour data's mean
      episode return (``data["behaviour_mean_return"]``), so that a fall that is real but small beside what the run
      learned (0.3 of MountainCar's return of 93, say) is not flagged.

    ``{"fell": bool, "step", "return", "return_ci", "best_step", "best_return", "best_return_ci",
    "behaviour_mean_return"}``; ``fell`` is ``False`` with fewer than two evaluations, without the behaviour data's
    return (LQR, scored by its regret against the exact optimum) or when a figure is missing or not finite."""
    ref = data.get("behaviour_mean_return")
    evals = [r for r in history if r.get("stage") == "q" and _finite(r.get("return")) and _finite(r.get("return_ci"))]
    if len(evals) < 2 or not _finite(ref):
        return {"fell": False}
    last, best = evals[-1], max(evals[:-1], key=lambda r: r["return"])
    fall = best["return"] - last["return"]
    disjoint = best["return"] - best["return_ci"] > last["return"] + last["return_ci"]
    material = fall >= RETURN_FALL_FRACTION * (best["return"] - ref) > 0
    return {"fell": bool(disjoint and material),
            "step": last["step"], "return": last["return"], "return_ci": last["return_ci"],
            "best_step": best["step"], "best_return": best["return"], "best_return_ci": best["return_ci"],
            "behaviour_mean_return": ref}


def load_results(root, *, finished_only: bool = False) -> list[dict]:
    """Every ``results.json`` under ``root`` (a Hydra multirun directory, or any tree of run directories); a
    multi-seed run's (``seeds=[...]``) counts as its seeds' runs.

    ``finished_only``: keep runs whose ``"status"`` is ``"finished"`` (results written before statuses existed
    count as finished); see :func:`split_by_status` to count the others.
    """
    import json
    from pathlib import Path

    loaded = []
    for path in sorted(Path(root).rglob(RESULTS)):
        try:
            loaded.append((path, json.loads(path.read_text())))
        except json.JSONDecodeError as err:
            raise ValueError(f"{path} is not valid JSON ({err}).") from err
    # a multi-seed run (``seeds=[...]``, ``"kind": "seeds"``) stands for its seeds' runs, each read once
    seed_paths = {id(run): path.parent / f"seed{run['seed']}" / RESULTS
                  for path, record in loaded if record.get("kind") == "seeds" for run in record.get("runs", [])}
    covered = {p.resolve() for p in seed_paths.values()}
    # a seed<s>/ folder beside a multi-seed run's record that the record does not list is not one of its runs
    multi = {path.parent.resolve() for path, record in loaded if record.get("kind") == "seeds"}
    records = []
    for path, record in loaded:
        if record.get("kind") == "seeds":
            records.extend({**run, "_path": str(seed_paths[id(run)])} for run in record.get("runs", []))
        elif path.parent.parent.resolve() in multi and path.parent.name.startswith("seed"):
            continue
        elif path.resolve() not in covered:
            record.setdefault("_path", str(path))
            records.append(record)
    if not records:
        raise FileNotFoundError(f"No results.json under {root}: did the runs finish?")
    return split_by_status(records)[0] if finished_only else records


def split_by_status(records: list[dict]) -> tuple[list[dict], list[dict]]:
    """``(finished, other)``: runs with ``"status": "finished"`` (or none recorded) and the rest (diverged, ...)."""
    finished = [r for r in records if r.get("status", "finished") == "finished"]
    return finished, [r for r in records if r.get("status", "finished") != "finished"]


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


def per_seed_cell(records: list[dict], path: str, digits: int = 1) -> str:
    """Each run's number at dotted ``path``, in seed order: ``"seed: value"``, with ``@step``, the step whose
    parameters the run delivered (``final.selected_step``, where ``q.select`` selects), and its flags in
    parentheses."""
    cells = []
    for rec in sorted(records, key=lambda r: (r.get("seed") is None, r.get("seed") or 0)):
        value = _lookup(rec, path)
        cell = f"{rec.get('seed', '?')}: {_n(value, f'.{digits}f')}"
        step = _lookup(rec, "final.selected_step")
        if isinstance(step, int):
            cell += f" @{step}"
        if rec.get("flags"):
            cell += f" ({', '.join(rec['flags'])})"
        cells.append(cell)
    return ", ".join(cells)


def results_table(records: list[dict], group_by: list[str], metrics: dict[str, str], *, digits: int = 4,
                  per_seed: str | None = None) -> str:
    """A Markdown table: one row per distinct value of ``group_by`` (config paths), ``mean ± 95% CI`` over seeds.

    ``metrics`` maps a column title to a dotted path in the results (e.g. ``{"regret": "final.regret"}``). The CI is
    Student-t over the runs of a row (the seeds), so it states how much the figure moves from seed to seed. Only
    finished runs enter the figures: runs with another ``"status"`` (diverged) are counted in a line below the
    table, and when a run is flagged (any of its ``flags``) a ``flagged`` column counts them per row. ``per_seed``: a
    column title of ``metrics`` whose values are also listed seed by seed (:func:`per_seed_cell`).
    """
    if per_seed is not None and per_seed not in metrics:
        raise ValueError(f"per_seed={per_seed!r} is not one of the table's metrics {sorted(metrics)}.")
    records, excluded = split_by_status(records)
    rows: dict[tuple, list[dict]] = {}
    for rec in records:
        key = tuple(_lookup(rec, "config." + g) if not g.startswith("=") else _lookup(rec, g[1:]) for g in group_by)
        rows.setdefault(key, []).append(rec)
    flagged = any(r.get("flags") for r in records)
    header = ([g.lstrip("=") for g in group_by] + ["seeds"] + (["flagged"] if flagged else []) + list(metrics)
              + ([f"{per_seed}, per seed"] if per_seed is not None else []))
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for key in sorted(rows, key=lambda k: tuple(str(x) for x in k)):
        recs = rows[key]
        cells = [str(k) for k in key] + [str(len(recs))]
        if flagged:
            cells.append(str(sum(1 for r in recs if r.get("flags"))))
        cells += [ci_cell(recs, path, digits) for path in metrics.values()]
        if per_seed is not None:
            cells.append(per_seed_cell(recs, metrics[per_seed], digits))
        lines.append("| " + " | ".join(cells) + " |")
    if excluded:
        counts: dict[str, int] = {}
        for r in excluded:
            counts[r.get("status")] = counts.get(r.get("status"), 0) + 1
        detail = ", ".join(f"{n} {status}" for status, n in sorted(counts.items(), key=str))
        lines.append(f"\n{len(excluded)} run(s) excluded from the table ({detail}).")
    return "\n".join(lines)
