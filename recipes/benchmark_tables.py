"""The benchmark table: algorithms × benchmark tasks, D4RL-normalised scores with 95% CIs over seeds, and the cost.

    python -m torchrl_wbrm.data.benchmark --data-path datasets/benchmark      # the datasets, once (about 1 min)
    python recipes/benchmark_tables.py --data-path datasets/benchmark         # wbrm on every task, 5 seeds
    python recipes/benchmark_tables.py --algos wbrm brm td3bc iql bc --seeds 5 --budgets 1 3 10
    python recipes/benchmark_tables.py --quick                                # a smoke version (CI): tiny data
    python recipes/benchmark_tables.py --report-only                          # rebuild tables.md from finished runs
    python recipes/benchmark_tables.py --few-demonstrations --tasks pendulum --expert-episodes 3 --expert-shares 10

With ``--few-demonstrations`` the table is the few-demonstration one (:func:`few_demonstration_cells`): per task,
``S^e`` = ``--expert-episodes`` episodes of the expert pool (``env.minari.expert_episodes``, drawn by each seed) and
``D`` a ``behaviour-expert<pp>-v0`` set (``--expert-shares``), every method of :data:`FEW_DEMONSTRATION_METHODS` on
it at the default budget; ``tables.md`` gives per cell and method the normalised score (mean ± 95% CI and each
seed's) and the wall seconds per run (``--out`` default ``results/few_demonstrations``).

Every run is the main recipe with the dataset keys only (``env=minari env.minari.expert=... env.minari.behaviour=...``)
plus ``algo=<name>``; ``--budgets`` multiplies the env's default ``q.steps`` (and ``q.eval_every``), to check that a
longer run does not lose return. Runs go through the studies' shared runner
(:func:`studies.runs.run_cells` (``recipes/studies/runs.py``): a cell's seeds in one process) into
``<out>/<task>/<algo>/x<budget>/seed<seed>``; a finished run is not run again. ``tables.md`` then gives, per task
and algorithm, the normalised score (0 = uniform random actions, 100 = the expert; the datasets' Minari reference
scores) as mean ± 95% CI over seeds, the raw return, the behaviour data's own score, how many runs were flagged
(``q_blow_up``, ``below_behaviour``, ``return_fell``, ``ratio_collapse``) and the wall seconds per run (one torch
thread, ``--jobs`` processes at a time; seeds trained in one process share its time equally).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # a clone's recipes run without installing (the package is importable either way)

LABELS = ("task", "algo", "budget")
#: the settings ``--budgets`` multiplies (a whole number each, from the task's defaults or ``--overrides``)
BUDGET_KEYS = ("q.steps", "q.eval_every")

#: the few-demonstration table's rows: name -> the overrides after the dataset keys (every method at the default budget)
FEW_DEMONSTRATION_METHODS = {
    "wbrm": ["algo=wbrm"],                                   # the default recipe
    "brm": ["algo=brm"],                                     # the same with ŵ ≡ 1
    # the actor also clones D's expert-like episodes, as the stage-1 ŵ ranks them (ŵ ≡ 1 adds none: "brm")
    "wbrm_from_d": ["algo=wbrm", "q.expert_bc_from_d=true"],
    "bc": ["algo=bc"],                                       # cloning S^e
    "bc_union": ["algo=bc", "baselines.bc.data=union"],      # cloning S^e ∪ D
    # cloning S^e ∪ D, D's rows weighted by the untempered ŵ (as ISW-BC weights by its ratio)
    "bc_weighted": ["algo=bc", "baselines.bc.data=weighted", "ratio.temper=1"],
    # cloning S^e and D's expert-like episodes, as the stage-1 ŵ finds them (ŵ ≡ 1 finds none: "bc")
    "bc_expert_like": ["algo=bc", "baselines.bc.data=expert_like"],
    "td3bc": ["algo=td3bc"],
    "iql": ["algo=iql"],
    "cql": ["algo=cql"],
    "bc_oracle": ["algo=bc", "baselines.bc.data=oracle"],    # cloning S^e and D's true expert episodes
}

FEW_LABELS = ("task", "cell", "method")


def _share(value: str) -> str:
    """``--expert-shares``: ``medium`` or a percentage written with two digits (``05``)."""
    if value == "medium" or (len(value) == 2 and value.isdigit() and value != "00"):
        return value
    raise argparse.ArgumentTypeError(f"{value!r}: a percentage with two digits (01 to 99) or 'medium'")


def dataset_overrides(data_path: Path, expert: str, behaviour: str) -> list[str]:
    """The dataset keys of a run on benchmark datasets: ``env=minari``, where the datasets are, and the ids of S^e's and
    D's datasets."""
    return ["env=minari", f"env.minari.data_path={data_path}", f"env.minari.expert={expert}",
            f"env.minari.behaviour={behaviour}"]


def flagged_and_wall(recs: list[dict]) -> tuple[str, str]:
    """A table row's "flagged" cell (how many of its runs were flagged, and with which flags) and its mean wall seconds
    per run."""
    from torchrl_wbrm.evaluation.stats import mean_ci

    flags = sorted({f for r in recs for f in r.get("flags", [])})
    flagged = sum(1 for r in recs if r.get("flags"))
    wall = [r["wall_seconds"] for r in recs if isinstance(r.get("wall_seconds"), (int, float))]
    return f"{flagged}{' (' + ', '.join(flags) + ')' if flags else ''}", f"{mean_ci(wall).mean:.0f}" if wall else "–"


def build_cells(tasks: list[str], algos: list[str], budgets: list[int], data_path: Path, namespace: str,
                base_steps: int, base_eval_every: int) -> list[dict]:
    from torchrl_wbrm.data.benchmark import benchmark_ids

    cells = []
    for task in tasks:
        ids = benchmark_ids(task, namespace)
        for algo in algos:
            for budget in budgets:
                overrides = [*dataset_overrides(data_path, ids["expert"], ids["behaviour"]), f"algo={algo}", "logger=none"]
                if budget != 1:
                    overrides += [f"q.steps={budget * base_steps}", f"q.eval_every={budget * base_eval_every}"]
                cells.append({"task": task, "algo": algo, "budget": f"x{budget}", "overrides": overrides})
    return cells


def few_demonstration_cells(tasks: list[str], expert_episodes: list[int], shares: list[str], methods: list[str],
                            data_path: Path, namespace: str, budgets: tuple[int, ...] = (1,), base_steps: int = 0,
                            base_eval_every: int = 0) -> list[dict]:
    """Every (task, S^e size, expert share of D, budget, method) cell: ``S^e`` = ``n`` episodes of the task's expert
    pool drawn by the seed, ``D`` its ``behaviour-expert<pp>-v0`` set (``medium-v0`` for the share ``"medium"``), the
    method's overrides (:data:`FEW_DEMONSTRATION_METHODS`) at ``budget`` times ``base_steps`` (and
    ``base_eval_every``); the cell label is ``se<n>_expert<pp>`` (``se<n>_medium``), with ``_x<budget>`` beyond the
    default budget."""
    from torchrl_wbrm.data.benchmark import few_demonstration_ids
    from torchrl_wbrm.data.locomotion import LOCOMOTION_DATASETS, locomotion_ids

    unknown = [m for m in methods if m not in FEW_DEMONSTRATION_METHODS]
    if unknown:
        raise ValueError(f"--methods {' '.join(unknown)}: not a method of the few-demonstration table; choose from "
                         f"{', '.join(FEW_DEMONSTRATION_METHODS)}.")
    if "medium" in shares and "bc_oracle" in methods:
        raise ValueError("--expert-shares medium with --methods bc_oracle: medium-v0 has no expert episodes to clone "
                         "(each step is the expert's with probability ½).")
    cells = []
    for task in tasks:
        locomotion = task in LOCOMOTION_DATASETS  # D = random-expert<pp>-v0 (a share of the transitions)
        ids = (locomotion_ids(task, namespace, [int(s) for s in shares if s != "medium"]) if locomotion
               else few_demonstration_ids(task, namespace))
        for n in expert_episodes:
            for share in shares:
                label = "medium" if share == "medium" else f"expert{share}"  # the cell's label
                name = f"{'random' if locomotion else 'behaviour'}_expert{int(share):02d}" if share != "medium" else ""
                if share != "medium" and name not in ids:
                    raise ValueError(f"--expert-shares {share}: task {task!r} has no "
                                     f"{name.replace('_', '-')}-v0 set (the small tasks have 05, 10 and 20).")
                behaviour = ids["medium"] if share == "medium" else ids[name]
                data = [*dataset_overrides(data_path, ids["expert_pool"], behaviour),
                        f"env.minari.expert_episodes={n}", "logger=none"]
                for budget in budgets:
                    steps = [] if budget == 1 else [f"q.steps={budget * base_steps}",
                                                    f"q.eval_every={budget * base_eval_every}"]
                    cell = f"se{n}_{label}" + ("" if budget == 1 else f"_x{budget}")
                    for method in methods:
                        cells.append({"task": task, "cell": cell, "method": method,
                                      "overrides": data + FEW_DEMONSTRATION_METHODS[method] + steps})
    return cells


def few_demonstrations_report(out: Path) -> str:
    """``tables.md`` of the few-demonstration table: per task, cell and method (in the order of
    :data:`FEW_DEMONSTRATION_METHODS`), the normalised score as mean ± 95% CI over the seeds and each seed's, the
    flags and the wall seconds per run."""
    from torchrl_wbrm.training.reporting import ci_cell, load_results, split_by_status

    records, excluded = split_by_status(load_results(out))
    rows: dict[tuple, list[dict]] = {}
    for rec in records:
        study = rec.get("study", {})
        if "method" in study:
            rows.setdefault((study.get("task"), study.get("cell"), study.get("method")), []).append(rec)
    order = list(FEW_DEMONSTRATION_METHODS)
    lines = ["| task | cell | method | seeds | normalised score | per seed | flagged | wall s / run |",
             "|---|---|---|---|---|---|---|---|"]
    for key in sorted(rows, key=lambda k: (str(k[0]), str(k[1]), order.index(k[2]) if k[2] in order else len(order))):
        recs = sorted(rows[key], key=lambda r: r.get("seed", 0))
        per_seed = ", ".join(f"{r['seed']}: {r['final']['normalised_score']:.1f}" for r in recs
                             if isinstance(r.get("final", {}).get("normalised_score"), (int, float)))
        flagged, wall = flagged_and_wall(recs)
        lines.append(f"| {key[0]} | {key[1]} | {key[2]} | {len(recs)} | "
                     f"{ci_cell(recs, 'final.normalised_score', 1)} | {per_seed} | {flagged} | {wall} |")
    lines += ["", *paired_differences(rows)]
    if excluded:
        lines.append(f"\n{len(excluded)} run(s) excluded (not finished: diverged or interrupted).")
    return "\n".join(lines) + "\n"


#: the paired differences the few-demonstration table reports: (method, against); the last is the ratio's other use,
#: D's expert-like episodes (as stage 1's ŵ ranks them) cloned beside S^e
PAIRS = (("wbrm", "brm"), ("wbrm", "bc"), ("brm", "bc"), ("bc_expert_like", "bc"))


def paired_differences(rows: dict[tuple, list[dict]]) -> list[str]:
    """The table of paired differences: per task and cell, ``method − against`` in normalised score over the seeds
    both ran (same seed: same S^e draw, same data), mean ± 95% Student-t interval and each seed's."""
    from torchrl_wbrm.evaluation.stats import mean_ci

    lines = ["| task | cell | difference | seeds | mean ± 95% CI | per seed |", "|---|---|---|---|---|---|"]
    cells = sorted({key[:2] for key in rows}, key=str)
    for task, cell in cells:
        for method, against in PAIRS:
            score = {name: {r["seed"]: r["final"]["normalised_score"] for r in rows.get((task, cell, name), [])
                            if isinstance(r.get("final", {}).get("normalised_score"), (int, float))}
                     for name in (method, against)}
            seeds = sorted(set(score[method]) & set(score[against]))
            if not seeds:
                continue
            diffs = [score[method][s] - score[against][s] for s in seeds]
            ci = mean_ci(diffs)
            cell_ci = f"{ci.mean:+.1f}" + (f" ± {ci.half_width:.1f}" if len(diffs) > 1 else "")
            lines.append(f"| {task} | {cell} | {method} − {against} | {len(seeds)} | {cell_ci} | "
                         + ", ".join(f"{s}: {d:+.1f}" for s, d in zip(seeds, diffs)) + " |")
    return lines if len(lines) > 2 else []


def few_demonstrations_plot(out: Path, against: str = "episodes") -> Path | None:
    """The normalised score of each method (a line each: mean and 95% Student-t interval over the seeds) at the
    default budget; dotted: the expert (100) and random actions (0). ``None`` (nothing drawn) when no cell has runs.

    ``against="episodes"``: ``few_demonstrations.png``, a panel per task and expert share of ``D``, against
    ``S^e``'s number of episodes. ``against="share"``: ``expert_share.png``, a panel per task and ``S^e`` size
    with runs at two shares or more, against the expert's share of ``D`` in percent (the ``medium-v0`` cells left
    out)."""
    import re

    import matplotlib.pyplot as plt

    from torchrl_wbrm.evaluation.stats import mean_ci
    from torchrl_wbrm.training.plots import save_figure
    from torchrl_wbrm.training.reporting import load_results, split_by_status

    if against not in ("episodes", "share"):
        raise ValueError(f"against={against!r}: 'episodes' or 'share'.")
    records, _ = split_by_status(load_results(out))
    scores: dict[tuple, dict[str, dict[int, list[float]]]] = {}
    for rec in records:
        study = rec.get("study", {})
        match = re.fullmatch(r"se(\d+)_(expert(\d+)|medium)", str(study.get("cell", "")))  # default budget only
        score = rec.get("final", {}).get("normalised_score")
        if not match or not isinstance(score, (int, float)) or (against == "share" and not match.group(3)):
            continue
        episodes, share = int(match.group(1)), match.group(2)
        panel, x = ((share, episodes) if against == "episodes" else (episodes, int(match.group(3))))
        methods = scores.setdefault((study["task"], panel), {})
        methods.setdefault(study["method"], {}).setdefault(x, []).append(score)
    if against == "share":  # a panel with one share has nothing to draw a line across
        scores = {panel: methods for panel, methods in scores.items()
                  if len({x for xs in methods.values() for x in xs}) > 1}
    if not scores:
        return None
    order = list(FEW_DEMONSTRATION_METHODS)
    fig, axes = plt.subplots(1, len(scores), figsize=(5.2 * len(scores), 3.8), squeeze=False)
    for ax, ((task, panel), methods) in zip(axes[0], sorted(scores.items(), key=lambda kv: str(kv[0]))):
        for method in sorted(methods, key=lambda m: order.index(m) if m in order else len(order)):
            xs = sorted(methods[method])
            cis = [mean_ci(methods[method][x]) for x in xs]
            ax.errorbar(xs, [c.mean for c in cis], yerr=[c.half_width for c in cis], marker="o", capsize=3,
                        label=f"{method} ({'/'.join(str(len(methods[method][x])) for x in xs)} seeds)")
        for level in (0.0, 100.0):
            ax.axhline(level, color="k", ls=":", lw=0.8)
        ax.set_xscale("log")
        ax.set_xticks(sorted({x for m in methods.values() for x in m}))
        ax.set_xticklabels([str(x) for x in ax.get_xticks()])
        ax.set_ylabel("normalised score (0 random, 100 expert)")
        if against == "episodes":
            ax.set_xlabel("S^e: expert episodes")
            ax.set_title(f"{task}, D " + ("medium-v0" if panel == "medium" else f"{int(panel[6:])}% expert"),
                         fontsize=10)
        else:
            ax.set_xlabel("the expert's share of D (%)")
            ax.set_title(f"{task}, S^e of {panel} expert episodes", fontsize=10)
        ax.legend(fontsize=7)
    return save_figure(fig, out / ("few_demonstrations.png" if against == "episodes" else "expert_share.png"))


def benchmark_report(out: Path) -> str:
    """``tables.md``'s text from every run under ``out``."""
    from torchrl_wbrm.training.reporting import ci_cell, load_results, split_by_status

    records, excluded = split_by_status(load_results(out))
    rows: dict[tuple, list[dict]] = {}
    for rec in records:
        study = rec.get("study", {})
        rows.setdefault((study.get("task"), study.get("algo"), study.get("budget")), []).append(rec)
    lines = [
        "| task | algo | budget | seeds | normalised score | return | behaviour data (normalised) | flagged | "
        "wall s / run |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for key in sorted(rows, key=lambda k: tuple(str(x) for x in k)):
        recs = rows[key]
        flagged, wall = flagged_and_wall(recs)
        lines.append(
            f"| {key[0]} | {key[1]} | {key[2]} | {len(recs)} | {ci_cell(recs, 'final.normalised_score', 1)} | "
            f"{ci_cell(recs, 'final.return', 1)} | {ci_cell(recs[:1], 'final.data_behaviour_normalised_score', 1)} | "
            f"{flagged} | {wall} |")
    if excluded:
        lines.append(f"\n{len(excluded)} run(s) excluded (not finished: diverged or interrupted).")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    from torchrl_wbrm.data.benchmark import BENCHMARK_TASKS, NAMESPACE
    from torchrl_wbrm.data.locomotion import LOCOMOTION_DATASETS

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data-path", default="datasets/benchmark", help="the benchmark's Minari data path")
    parser.add_argument("--namespace", default=NAMESPACE)
    parser.add_argument("--tasks", nargs="+", default=list(BENCHMARK_TASKS),
                        choices=[*BENCHMARK_TASKS, *LOCOMOTION_DATASETS],
                        help="the locomotion tasks (datasets made by python -m torchrl_wbrm.data.benchmark --tasks "
                             "...) with --few-demonstrations only")
    parser.add_argument("--algos", nargs="+", default=["wbrm"])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--budgets", nargs="+", type=int, default=[1], help="multiples of the default q.steps")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--out", default=None, help="default: results/benchmark (results/few_demonstrations)")
    parser.add_argument("--quick", action="store_true", help="tiny datasets and budgets (a smoke run)")
    parser.add_argument("--few-demonstrations", action="store_true",
                        help="the few-demonstration table: S^e a few episodes of the expert pool, D a behaviour set "
                             "with a share of expert episodes, every method of FEW_DEMONSTRATION_METHODS")
    parser.add_argument("--expert-episodes", nargs="+", type=int, default=[3], help="S^e's episodes (few-demos)")
    parser.add_argument("--expert-shares", nargs="+", default=["10"], type=_share,
                        help="the expert share of D in percent (two digits), behaviour-expert<pp>-v0 (the small "
                             "tasks: 05, 10, 20) or random-expert<pp>-v0 (locomotion), or medium: medium-v0 "
                             "(few-demonstrations)")
    parser.add_argument("--methods", nargs="+", default=list(FEW_DEMONSTRATION_METHODS),
                        help="the few-demonstration table's rows")
    parser.add_argument("--overrides", nargs="+", default=[], metavar="KEY=VALUE",
                        help="recipe overrides for every run, before each cell's own; a q.steps or q.eval_every "
                             "given here is what --budgets multiplies")
    parser.add_argument("--report-only", action="store_true")
    from studies.docs_fragments import add_docs_dir_argument, docs_dir_from_args, publish_study

    add_docs_dir_argument(parser)
    args = parser.parse_args(argv)
    pairs = [o.split("=", 1) for o in args.overrides]
    malformed = [o for o, kv in zip(args.overrides, pairs) if len(kv) != 2 or not kv[0]]
    if malformed:
        parser.error(f"--overrides {' '.join(malformed)}: each must be KEY=VALUE (e.g. q.layer_norm=false).")
    base_settings = {k: v for k, v in pairs if k in BUDGET_KEYS}
    fractional = [f"{k}={v}" for k, v in base_settings.items() if not v.isdigit()]
    if fractional:
        parser.error(f"--overrides {' '.join(fractional)}: {' and '.join(BUDGET_KEYS)} must be whole numbers "
                     f"(--budgets multiplies them).")

    from torchrl_wbrm.data.benchmark import benchmark_ids, make_benchmark
    from torchrl_wbrm.data.minari_data import minari_data_root
    from torchrl_wbrm.tasks import MinariTask
    from studies.runs import run_cells

    few = args.few_demonstrations
    locomotion = few and all(t in LOCOMOTION_DATASETS for t in args.tasks)  # the locomotion page's table
    out = Path(args.out or ("results/locomotion" if locomotion else "results/few_demonstrations" if few
                            else "results/benchmark")).resolve()
    data_path = Path(args.data_path).resolve()
    if not args.report_only:
        from torchrl_wbrm.data.benchmark import few_demonstration_ids

        made = (lambda t: few_demonstration_ids(t, args.namespace)["expert_pool"]) if few else (
            lambda t: benchmark_ids(t, args.namespace)["behaviour"])
        missing = [t for t in args.tasks if not (minari_data_root(data_path) / made(t)).exists()]
        unmade = [t for t in missing if t in LOCOMOTION_DATASETS]  # hours of data: never made as a side effect
        if unmade:
            parser.error(f"--data-path {data_path}: no {made(unmade[0])} there (tasks {' '.join(unmade)}); make "
                         f"the datasets with python -m torchrl_wbrm.data.benchmark --data-path {data_path} --tasks "
                         f"{' '.join(unmade)}, or give the data path they were made in.")
        if missing:
            sizes = dict(expert_episodes=2, behaviour_episodes=10, reference_episodes=3) if args.quick else {}
            rows = make_benchmark(data_path, tasks=missing, namespace=args.namespace, **sizes)
            print(f"wrote the datasets of {', '.join(r['task'] for r in rows)} under {data_path}")
        steps, eval_every = (int(base_settings.get(k, getattr(MinariTask.TRAINING_DEFAULTS.q, k.split(".")[1])))
                             for k in BUDGET_KEYS)
        if few:
            cells = few_demonstration_cells(args.tasks, args.expert_episodes, args.expert_shares, args.methods,
                                            data_path, args.namespace, args.budgets, steps, eval_every)
        else:
            cells = build_cells(args.tasks, args.algos, args.budgets, data_path, args.namespace, steps, eval_every)
        budget = [*args.overrides, *(["ratio.steps=20", "q.steps=20", "q.eval_every=10", "eval.episodes=2",
                                      "eval.train_episodes=1", "plots=false"] if args.quick else [])]
        if args.quick:  # the budget goes first, so a cell's own q.steps (its multiple) would win: drop it
            for cell in cells:
                cell["overrides"] = [o for o in cell["overrides"] if o.split("=", 1)[0] not in BUDGET_KEYS]
        run_cells(cells, range(args.seeds), budget, out, jobs=args.jobs, labels=FEW_LABELS if few else LABELS)
    table = few_demonstrations_report(out) if few else benchmark_report(out)
    (out / "tables.md").parent.mkdir(parents=True, exist_ok=True)
    (out / "tables.md").write_text(table)
    print(table)
    from torchrl_wbrm.training.reporting import load_results

    base = (f"`q.steps={base_settings['q.steps']}`" if "q.steps" in base_settings
            else "the task's default `q.steps`")
    budget = (base if few else ", ".join(f"×{b}" for b in args.budgets) + " " + base) + (
        f"; every run with `{' '.join(args.overrides)}`" if args.overrides else "")
    # the locomotion table's figure: score against the expert's share of D (once it has two shares or more)
    figures = ([few_demonstrations_plot(out, "share")] if len(args.expert_shares) > 1 else []) if locomotion else (
        [few_demonstrations_plot(out)] if few else [])
    publish_study("locomotion" if locomotion else "few_demonstrations" if few else "benchmark", out / "tables.md",
                  docs_dir_from_args(args.docs_dir, args.quick), figures=figures,
                  seeds={r["seed"] for r in load_results(out) if "seed" in r},
                  argv=None if argv is None else [sys.argv[0], *argv],
                  budget=budget
                  + (" (`--quick`: `ratio.steps=20`, `q.steps=20`, 2 evaluation episodes)" if args.quick else ""))


if __name__ == "__main__":
    main()
