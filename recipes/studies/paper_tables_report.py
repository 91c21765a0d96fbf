"""The paper tables' report: ``tables.md`` and the figures, read from the finished runs of
``recipes/paper_tables.py`` (which runs them and calls :func:`report`). Nothing here trains.

``tables.md``: Table 2 (LQR: mean 20-step discounted return ± 95% CI per algorithm and LQR env, beside each env's
exact optimum and the paper's figures), the paired regret, Q̂'s error relative to Q*'s spread and Q̂'s overestimation
bias mean(Q̂ − Q*) on behaviour and expert data (every LQR env that ran: an env is LQR when its runs' config says
``env.kind: lqr``), Table 3 (MountainCar: mean return over 100 episodes ± 95% CI), the cost, and "budget and
convergence" (:func:`convergence_table`), the budget check (:func:`budget_table`) and the headline
(:func:`headline_table`, first). ``paper_tables.png`` draws the final figures, ``learning_curves.png``
(:func:`plot_learning_curves`) each algorithm's evaluations during training, from each run's ``history.json``.
"""
from __future__ import annotations

import json
from pathlib import Path

PAPER_TABLE_2 = {  # Table 2 of the paper (one run each, no error bars)
    "dqn": (85.09, 84.32, 84.57),
    "ddpg": (84.74, 85.49, 86.20),
    "mabo": (85.02, 85.64, 84.64),
    "wbrm": (86.65, 86.74, 87.10),
}
PAPER_TABLE_3 = {"dqn": 94.67, "ddpg": 95.29, "mabo": 94.78, "wbrm": 95.51}

def budget_check_dir(out: Path) -> Path:
    """Where the budget check's runs live: beside ``out`` (``<out>_budget_check/steps<N>/<env>/<algo>/seed<s>``), so
    that the tables, which read every run under ``out``, do not mix budgets."""
    return out.with_name(out.name + "_budget_check")


def _algo(record: dict) -> str:
    return record.get("algo", "wbrm")


def is_lqr(record: dict) -> bool:
    """An LQR run: its saved config says ``env.kind: lqr`` (results without a config: its final figures have the
    exact optimum, which only LQR has)."""
    kind = ((record.get("config") or {}).get("env") or {}).get("kind")
    return kind == "lqr" if kind is not None else "optimal_return_exact" in (record.get("final") or {})


def split_envs(records: list[dict]) -> tuple[list[str], list[str]]:
    """``(lqr_envs, other_envs)`` that ran, each sorted by name (the paper's exp1-3 come before ``lqr_nondiag``)."""
    lqr = sorted({r["env"] for r in records if is_lqr(r)})
    return lqr, sorted({r["env"] for r in records} - set(lqr))


def tables(out: Path) -> str:
    from torchrl_wbrm.training.reporting import ci_cell, load_results

    records = load_results(out)
    by = by_algo_env(records)
    algos = sorted({a for a, _ in by})
    lqr_envs, other_envs = split_envs(records)

    def cell(algo, env, path, digits=3):
        return ci_cell(by.get((algo, env), []), path, digits)

    parts = [headline_table(records)]
    if lqr_envs:
        optimum = {e: "–" if (v := exact_optimum(records, e)) is None else f"{v:.3f}" for e in lqr_envs}
        head = "| algorithm | " + " | ".join(f"{e} return" for e in lqr_envs) + " | paper (exp1, exp2, exp3) |"
        lines = [head, "|" + "---|" * (len(lqr_envs) + 2)]
        lines.append("| exact optimum | " + " | ".join(optimum[e] for e in lqr_envs) + " | 87.84 (the reward cap) |")
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
    if "mountain_car" in other_envs:
        lines = ["| algorithm | mean return (100 episodes) ± 95% CI over seeds | paper |", "|---|---|---|"]
        for a in algos:
            paper = f"{PAPER_TABLE_3[a]:.2f}" if a in PAPER_TABLE_3 else "–"
            lines.append(f"| {a} | {cell(a, 'mountain_car', 'final.return', 2)} | {paper} |")
        parts.append("### Table 3 (MountainCarContinuous-v0)\n\n" + "\n".join(lines))
    envs = lqr_envs + other_envs
    lines = ["| algorithm | " + " | ".join(envs) + " |", "|" + "---|" * (len(envs) + 1)]
    for a in algos:
        lines.append(f"| {a} | " + " | ".join(cell(a, e, "wall_seconds", 0) for e in envs) + " |")
    parts.append("### Cost: wall seconds per run (one torch thread; seeds trained in one process share its "
                 "time equally)\n\n" + "\n".join(lines))
    curves = learning_curves(records)
    if curves:
        parts.append("### Budget and convergence: the last evaluation against the earlier ones\n\n"
                     + convergence_table(curves))
    budget = table_budget(records)
    check = budget_table(out, budget) if budget is not None else ""
    if check:
        parts.append("### Budget check: the final figure at other budgets, each its own runs\n\n" + check)
    seeds = sorted({r["seed"] for r in records})
    timing = out / "wall_seconds.json"
    total = []
    took = json.loads(timing.read_text()) if timing.is_file() else {}
    if "wall_seconds" in took:
        total.append(f"The whole grid took {took['wall_seconds'] / 60:.1f} min.")
    if "budget_check_seconds" in took:
        total.append(f"The budget check took {took['budget_check_seconds'] / 60:.1f} min more.")
    total = " " + " ".join(total) if total else ""
    parts.append(f"Seeds: {seeds}. Paper figures are single runs without error bars.{total}")
    return "\n\n".join(parts)


def by_algo_env(records: list[dict]) -> dict[tuple[str, str], list[dict]]:
    """The runs of each (algorithm, env)."""
    by: dict[tuple[str, str], list[dict]] = {}
    for r in records:
        by.setdefault((_algo(r), r["env"]), []).append(r)
    return by


def exact_optimum(records: list[dict], env: str) -> float | None:
    """The env's exact optimal return: the same in every run of it (a diverged run may lack it); None if no run
    has one (not LQR)."""
    found = [r["final"]["optimal_return_exact"] for r in records
             if r["env"] == env and "optimal_return_exact" in (r.get("final") or {})]
    return found[0] if found else None


def table_budget(records: list[dict]) -> int | None:
    """The grid's ``q.steps`` (the most common over its runs; None without configs)."""
    from collections import Counter

    steps = Counter(((r.get("config") or {}).get("q") or {}).get("steps") for r in records)
    steps.pop(None, None)
    return steps.most_common(1)[0][0] if steps else None


def headline_table(records: list[dict]) -> str:
    """The headline: one row per algorithm, one column per env, the LQR envs' paired regret and the other envs'
    return, ``mean ± 95% CI`` over seeds, the best mean of each column in bold; the first row is the exact optimum
    (regret 0 at the optimal return the LQR Riccati solution gives; no exact optimum is known for MountainCar)."""
    import numpy as np

    from torchrl_wbrm.training.reporting import ci_cell

    by = by_algo_env(records)
    algos = sorted({a for a, _ in by})
    lqr_envs, other_envs = split_envs(records)
    columns = [(e, "regret", 4, min) for e in lqr_envs] + [(e, "return", 2, max) for e in other_envs]
    lines = ["| algorithm | " + " | ".join(f"{env} {key}" for env, key, _, _ in columns) + " |",
             "|" + "---|" * (len(columns) + 1)]
    optimum, best = [], {}
    for env, key, _, pick in columns:
        found = exact_optimum(records, env)
        optimum.append(f"0 (return {found:.3f})" if key == "regret" and found is not None else "– (none known)")
        means = {}
        for a in algos:
            values = [v for r in by.get((a, env), []) if isinstance(v := (r.get("final") or {}).get(key), (int, float))]
            if values:
                means[a] = float(np.mean(values))
        best[env] = pick(means, key=means.get) if means else None
    lines.append("| exact optimum | " + " | ".join(optimum) + " |")
    for a in algos:
        cells = [ci_cell(by.get((a, env), []), f"final.{key}", digits) for env, key, digits, _ in columns]
        cells = [f"**{c}**" if best[env] == a else c for c, (env, *_) in zip(cells, columns)]
        lines.append(f"| {a} | " + " | ".join(cells) + " |")
    return ("### Headline: every method on every environment (LQR: paired regret, lower is better; "
            "otherwise: return, higher is better)\n\n" + "\n".join(lines))


def learning_curves(records: list[dict]) -> dict[tuple[str, str], dict]:
    """Each (env, algorithm)'s curve over its finished runs, from the ``history.json`` beside each ``results.json``.

    A run's curve is its ``"stage": "q"`` records (``step`` and the figure: ``regret`` on LQR, ``return``
    elsewhere); the curve of an (env, algorithm) is, at every evaluation step, the mean over the seeds evaluated at
    that step with its 95% Student-t interval (:func:`torchrl_wbrm.evaluation.mean_ci`; none for one seed). Its
    ``budget`` is the runs' ``q.steps`` (from their saved config, sorted; one value unless the seeds differ). Runs
    without a history (or not finished) are left out. Returns ``{(env, algo): {"metric", "steps", "mean", "low",
    "high", "n", "budget", "runs", "run_cis"}}``: ``runs`` is each seed's ``{step: figure}``, ``run_cis`` its
    evaluations' own 95% half-widths over episodes (``<figure>_ci`` in the history), for :func:`curve_verdict`.
    """
    import math

    from torchrl_wbrm.evaluation import mean_ci
    from torchrl_wbrm.training.reporting import split_by_status

    runs: dict[tuple[str, str], list[tuple[dict, dict[int, float]]]] = {}
    for r in split_by_status(records)[0]:
        if "_path" not in r:
            continue
        path = Path(r["_path"]).with_name("history.json")
        if not path.is_file():
            continue
        metric = "regret" if is_lqr(r) else "return"
        points, cis = {}, {}
        for h in json.loads(path.read_text()):
            if h.get("stage") == "q" and isinstance(h.get(metric), (int, float)) and math.isfinite(h[metric]):
                points[int(h["step"])] = float(h[metric])
                if isinstance(h.get(f"{metric}_ci"), (int, float)) and math.isfinite(h[f"{metric}_ci"]):
                    cis[int(h["step"])] = float(h[f"{metric}_ci"])
        if points:
            runs.setdefault((r["env"], _algo(r)), []).append((r, points, cis))
    curves = {}
    for key, group in sorted(runs.items()):
        steps = sorted({s for _, points, _ in group for s in points})
        mean, low, high, n = [], [], [], []
        for s in steps:
            ci = mean_ci([points[s] for _, points, _ in group if s in points])
            mean.append(ci.mean)
            low.append(ci.low if ci.n > 1 else ci.mean)
            high.append(ci.high if ci.n > 1 else ci.mean)
            n.append(ci.n)
        budget = sorted({int(r["config"]["q"]["steps"]) for r, _, _ in group
                         if isinstance(((r.get("config") or {}).get("q") or {}).get("steps"), int)})
        curves[key] = {"metric": "regret" if is_lqr(group[0][0]) else "return", "steps": steps, "mean": mean,
                       "low": low, "high": high, "n": n, "budget": budget,
                       "runs": [points for _, points, _ in group], "run_cis": [cis for _, _, cis in group]}
    return curves


def change_interval(curve: dict, step: int, reference: int) -> tuple[float, float, float] | None:
    """The change of the figure from evaluation step ``reference`` to ``step``: ``(mean, low, high)`` of the
    per-seed differences, a paired 95% Student-t interval over the seeds evaluated at both. With one seed the
    interval is that run's two evaluations' own intervals (over episodes) combined, ±√(ci₁² + ci₂²) (±0 when the
    history has none). None when no seed was evaluated at both."""
    from torchrl_wbrm.evaluation import mean_ci

    pairs = [(points[step] - points[reference], cis.get(step, 0.0), cis.get(reference, 0.0))
             for points, cis in zip(curve["runs"], curve["run_cis"]) if step in points and reference in points]
    if not pairs:
        return None
    if len(pairs) == 1:
        d, c1, c2 = pairs[0]
        half = (c1 ** 2 + c2 ** 2) ** 0.5
        return d, d - half, d + half
    ci = mean_ci([d for d, _, _ in pairs])
    return ci.mean, ci.low, ci.high


def curve_verdict(curve: dict) -> dict:
    """Whether an (env, algorithm)'s curve had stopped changing at its last evaluation, beyond the noise.

    ``last`` is the seed-mean at the last evaluation step, ``previous`` at the one before, ``best`` the best
    (lowest regret, highest return) seed-mean of the evaluations before the last, at step ``best_step``. The
    changes ``vs_previous`` (last − previous) and ``vs_best`` (last − best) are :func:`change_interval`'s
    ``(mean, low, high)``: paired over seeds, so they hold both the seed-to-seed spread and each evaluation's noise
    over its episodes. The verdict: ``"past its best"`` when the last is worse than the best earlier one beyond its
    interval (regret: the interval above 0; return: below), else ``"still improving"`` when it is better than the
    previous one beyond its interval, else ``"flat"`` (no change the seeds can tell from noise); ``"one evaluation"``
    for a curve of one point. The best earlier step is picked from noisy means, so "past its best" leans towards
    being said. The last evaluation is the final one, on ``eval.episodes`` episodes; the earlier ones use
    ``eval.train_episodes`` (in the tables, LQR 200 against 1,000 and MountainCar 5 against 100): their wider
    intervals enter the comparison.
    """
    steps, mean, regret = curve["steps"], curve["mean"], curve["metric"] == "regret"
    out = {"last": mean[-1], "last_step": steps[-1], "previous": None, "best": None, "best_step": None,
           "vs_previous": None, "vs_best": None, "verdict": "one evaluation"}
    if len(steps) < 2:
        return out
    earlier = mean[:-1]
    pick = min if regret else max
    best_i = pick(range(len(earlier)), key=earlier.__getitem__)
    out.update(previous=earlier[-1], best=earlier[best_i], best_step=steps[best_i])
    out["vs_previous"] = change_interval(curve, steps[-1], steps[-2])
    out["vs_best"] = change_interval(curve, steps[-1], steps[best_i])
    sign = 1.0 if regret else -1.0  # a positive sign * change is worse

    def worse(c):
        return min(sign * c[1], sign * c[2]) > 0

    def better(c):
        return max(sign * c[1], sign * c[2]) < 0

    if out["vs_previous"] is None or out["vs_best"] is None:
        out["verdict"] = "n/a"
    elif worse(out["vs_best"]):
        out["verdict"] = "past its best"
    elif better(out["vs_previous"]):
        out["verdict"] = "still improving"
    else:
        out["verdict"] = "flat"
    return out


def convergence_table(curves: dict[tuple[str, str], dict]) -> str:
    """"Budget and convergence": one row per (env, algorithm): its budget (``q.steps``), the number of evaluations,
    the seed-mean figure at the previous and last evaluations and the best earlier one, and
    :func:`curve_verdict`'s changes (last − previous, last − best, each with its paired 95% interval) and verdict."""

    def fmt(v, regret):
        return "n/a" if v is None else (f"{v:.4f}" if regret else f"{v:.2f}")

    def change(c, regret):
        if c is None:
            return "n/a"
        d = 4 if regret else 2
        return f"{c[0]:+.{d}f} [{c[1]:+.{d}f}, {c[2]:+.{d}f}]"

    lines = ["| env | algorithm | figure | budget (q.steps) | evaluations | previous | last | best earlier (step) "
             "| last − previous [95% CI] | last − best earlier [95% CI] | verdict |", "|" + "---|" * 11]
    for (env, algo), curve in sorted(curves.items()):
        v, regret = curve_verdict(curve), curve["metric"] == "regret"
        budget = "/".join(map(str, curve["budget"])) or "?"
        best = "n/a" if v["best"] is None else f"{fmt(v['best'], regret)} ({v['best_step']})"
        lines.append(f"| {env} | {algo} | {curve['metric']} | {budget} | {len(curve['steps'])} "
                     f"| {fmt(v['previous'], regret)} | {fmt(v['last'], regret)} | {best} "
                     f"| {change(v['vs_previous'], regret)} | {change(v['vs_best'], regret)} | {v['verdict']} |")
    lines.append("\nSeed means at each evaluation step (the last is at the budget, on the final evaluation's episodes; "
                 "the earlier ones on eval.train_episodes). Each change is paired over seeds, with its 95% Student-t "
                 "interval (one seed: the two evaluations' own intervals combined). Flat: the change from the previous "
                 "evaluation is within its interval; still improving: better beyond it; past its best: worse than the "
                 "best earlier evaluation beyond its interval. See learning_curves.png.")
    return "\n".join(lines)


def budget_curves(out: Path) -> dict[tuple[str, str], dict]:
    """The budget check's finals: ``{(env, algo): {"metric", "runs": {steps: {seed: figure}}}}``, from the grid's runs
    (their ``q.steps``) and the runs under :func:`budget_check_dir`, for the envs the check ran."""
    from torchrl_wbrm.training.reporting import load_results, split_by_status

    check = budget_check_dir(out)
    if not check.is_dir() or not any(check.rglob("results.json")):
        return {}
    extra = split_by_status(load_results(check))[0]
    envs = {r["env"] for r in extra}
    curves: dict[tuple[str, str], dict] = {}
    for r in extra + [r for r in split_by_status(load_results(out))[0] if r["env"] in envs]:
        metric = "regret" if is_lqr(r) else "return"
        value = (r.get("final") or {}).get(metric)
        steps = ((r.get("config") or {}).get("q") or {}).get("steps")
        if isinstance(value, (int, float)) and isinstance(steps, int):
            curve = curves.setdefault((r["env"], _algo(r)), {"metric": metric, "runs": {}})
            curve["runs"].setdefault(steps, {})[r["seed"]] = float(value)
    return curves


def budget_verdict(curve: dict, budget: int) -> dict:
    """Whether ``budget`` sufficed: the final figure at the largest budget checked against the one at ``budget``,
    paired over the seeds run at both (a 95% Student-t interval of the differences). ``"converged"`` unless the
    larger budget is better beyond the interval (``"not converged"``); ``"worse with more steps"`` when it is worse
    beyond it; ``"n/a"`` without a larger budget or with fewer than two paired seeds."""
    from torchrl_wbrm.evaluation import mean_ci

    out = {"budget": budget, "longest": None, "change": None, "verdict": "n/a"}
    longer = [s for s in curve["runs"] if s > budget]
    if budget not in curve["runs"] or not longer:
        return out
    longest = max(longer)
    a, b = curve["runs"][budget], curve["runs"][longest]
    diffs = [b[s] - a[s] for s in sorted(set(a) & set(b))]
    out["longest"] = longest
    if len(diffs) < 2:
        return out
    ci = mean_ci(diffs)
    out["change"] = (ci.mean, ci.low, ci.high)
    sign = 1.0 if curve["metric"] == "regret" else -1.0  # sign * change > 0: worse
    if sign * ci.low > 0 and sign * ci.high > 0:
        out["verdict"] = "worse with more steps"
    elif sign * ci.low < 0 and sign * ci.high < 0:
        out["verdict"] = "not converged"
    else:
        out["verdict"] = "converged"
    return out


def budget_table(out: Path, budget: int) -> str:
    """"Budget check": per (env, algorithm) the final figure (mean ± 95% CI over seeds) at every budget run, the
    change from ``budget`` (the table's) to the largest, paired over seeds, and :func:`budget_verdict`. Empty when
    the check did not run."""
    from torchrl_wbrm.evaluation import mean_ci

    curves = budget_curves(out)
    if not curves:
        return ""
    steps = sorted({s for c in curves.values() for s in c["runs"]})
    lines = ["| env | algorithm | figure | " + " | ".join(f"{s} steps" + (" (table)" if s == budget else "")
                                                      for s in steps)
             + f" | largest − {budget} [95% CI] | verdict |", "|" + "---|" * (len(steps) + 5)]
    for (env, algo), curve in sorted(curves.items()):
        regret = curve["metric"] == "regret"
        d = 4 if regret else 2
        cells = []
        for s in steps:
            values = list(curve["runs"].get(s, {}).values())
            if not values:
                cells.append("–")
            elif len(values) == 1:
                cells.append(f"{values[0]:.{d}f}")
            else:
                ci = mean_ci(values)
                cells.append(f"{ci.mean:.{d}f} ± {ci.half_width:.{d}f}")
        v = budget_verdict(curve, budget)
        change = "n/a" if v["change"] is None else "{:+.{d}f} [{:+.{d}f}, {:+.{d}f}]".format(*v["change"], d=d)
        lines.append(f"| {env} | {algo} | {curve['metric']} | " + " | ".join(cells) + f" | {change} | {v['verdict']} |")
    lines.append(f"\nEach budget is its own runs (the learning rate is annealed over each budget), evaluated at the end "
                 f"on the same episodes; the {budget}-step column is the grid's runs. Converged: the largest budget is "
                 f"not better than the table's beyond the paired 95% interval over seeds. See budget_check.png.")
    return "\n".join(lines)


def plot_budget_check(out: Path, budget: int) -> Path | None:
    """``budget_check.png``: per env of the check, each algorithm's final figure against its budget (mean ± 95% CI
    over seeds; log-log for regret), the table's budget a dashed line. None when the check did not run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchrl_wbrm.training.plots import save_figure

    from torchrl_wbrm.evaluation import mean_ci

    curves = budget_curves(out)
    if not curves:
        return None
    envs = sorted({e for e, _ in curves})
    algos = sorted({a for _, a in curves})
    colours = {a: plt.get_cmap("tab10" if len(algos) <= 10 else "tab20")(i) for i, a in enumerate(algos)}
    fig, axes = plt.subplots(1, len(envs), figsize=(5.5 * len(envs), 4.0), squeeze=False)
    for ax, env in zip(axes[0], envs):
        regret = False
        for algo in algos:
            curve = curves.get((env, algo))
            if curve is None:
                continue
            regret = curve["metric"] == "regret"
            steps = sorted(curve["runs"])
            cis = [mean_ci(list(curve["runs"][s].values())) for s in steps]
            means = [c.mean for c in cis]
            errs = [0.0 if c.n < 2 else c.half_width for c in cis]
            ax.errorbar(steps, means, yerr=errs, marker="o", ms=4, capsize=3, color=colours[algo], label=algo)
        ax.axvline(budget, color="grey", ls="--", lw=0.8)
        ax.set_xscale("log")
        if regret:
            ax.set_yscale("log", nonpositive="clip")
        ax.set_xlabel("q.steps (each budget its own runs)")
        ax.set_title(f"{env}: final {'paired regret' if regret else 'return'}", fontsize=10)
        ax.legend(fontsize=7, ncol=2, frameon=False)
    fig.suptitle(f"budget check: mean ± 95% CI over seeds; dashed: the table's budget ({budget})", fontsize=10)
    return save_figure(fig, out / "budget_check.png")


def plot(out: Path) -> Path:
    """``paper_tables.png``: each LQR env's paired regret (log scale) and the other envs' return per algorithm,
    mean ± 95% CI."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchrl_wbrm.training.plots import plot_ci_rows, save_figure
    from torchrl_wbrm.training.reporting import load_results

    records = load_results(out)
    lqr_envs, other_envs = split_envs(records)
    envs = lqr_envs + other_envs
    algos = sorted({_algo(r) for r in records})
    fig, axes = plt.subplots(1, len(envs), figsize=(4.2 * len(envs), 0.35 * len(algos) + 1.8), squeeze=False)
    for ax, env in zip(axes[0], envs):
        key = "regret" if env in lqr_envs else "return"
        rows = {a: [r["final"][key] for r in records if r["env"] == env and _algo(r) == a
                    and isinstance((r.get("final") or {}).get(key), (int, float))] for a in algos}
        plot_ci_rows(ax, rows, log=key == "regret")
        label = "paired regret" if key == "regret" else ("return (100 episodes)" if env == "mountain_car" else "return")
        ax.set_title(f"{env}: {label}", fontsize=10)
    fig.suptitle("mean ± 95% CI over seeds (LQR: regret against the exact optimum)", fontsize=10)
    return save_figure(fig, out / "paper_tables.png")


def plot_learning_curves(out: Path, records: list[dict] | None = None) -> Path | None:
    """``learning_curves.png``: one panel per env, one line per algorithm (:func:`learning_curves`: the seed mean
    with its 95% CI band), regret on a log axis for LQR (a band reaching zero runs off the bottom of the axis),
    return otherwise; each algorithm's budget (its ``q.steps``) is a dashed vertical line in its colour. None (no
    figure) when no run has a history."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchrl_wbrm.training.plots import save_figure

    from torchrl_wbrm.training.reporting import load_results

    records = load_results(out) if records is None else records
    curves = learning_curves(records)
    if not curves:
        return None
    lqr_envs, other_envs = split_envs(records)
    envs = [e for e in lqr_envs + other_envs if any(env == e for env, _ in curves)]
    algos = sorted({a for _, a in curves})
    colours = {a: plt.get_cmap("tab10" if len(algos) <= 10 else "tab20")(i) for i, a in enumerate(algos)}
    fig, axes = plt.subplots(1, len(envs), figsize=(4.4 * len(envs), 3.6), squeeze=False)
    handles = {}
    for ax, env in zip(axes[0], envs):
        for algo in algos:
            curve = curves.get((env, algo))
            if curve is None:
                continue
            colour = colours[algo]
            (line,) = ax.plot(curve["steps"], curve["mean"], marker="o", ms=3, color=colour, label=algo)
            handles.setdefault(algo, line)
            ax.fill_between(curve["steps"], curve["low"], curve["high"], color=colour, alpha=0.15, lw=0)
            for budget in curve["budget"]:
                ax.axvline(budget, color=colour, ls="--", lw=0.8, alpha=0.6)
        regret = env in lqr_envs
        if regret:
            ax.set_yscale("log", nonpositive="clip")
        ax.set_title(f"{env}: {'paired regret' if regret else 'return'}", fontsize=10)
        ax.set_xlabel("Q step")
    fig.legend(list(handles.values()), list(handles), loc="lower center", ncol=min(len(handles), 10), fontsize=8,
               frameon=False)
    fig.suptitle("evaluations during training: mean ± 95% CI over seeds; dashed: each algorithm's budget (q.steps)",
                 fontsize=10)
    return save_figure(fig, out / "learning_curves.png", rect=(0, 0.08, 1, 1))


def report(out: Path) -> tuple[str, list[Path | None]]:
    """Write ``<out>/tables.md`` and the figures from the runs under ``out``; returns the tables' text and the
    figures' paths (``None`` for a figure with nothing to draw)."""
    from torchrl_wbrm.training.reporting import load_results

    text = tables(out)
    (out / "tables.md").write_text(text + "\n")
    budget = table_budget(load_results(out))
    figures = [plot(out), plot_learning_curves(out), plot_budget_check(out, budget) if budget is not None else None]
    return text, figures
