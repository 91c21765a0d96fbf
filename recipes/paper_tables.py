"""The paper's Tables 2 and 3, regenerated on identical data with seeds and confidence intervals.

    python recipes/paper_tables.py                    # all algorithms x {LQR exp1-3, LQR nondiag, MountainCar} x 5 seeds,
                                                      # then the budget check on LQR exp1
    python recipes/paper_tables.py --quick            # a smoke version (CI)
    python recipes/paper_tables.py --algos wbrm td3bc --envs lqr_exp1 --seeds 3
    python recipes/paper_tables.py --report-only      # rebuild tables.md and the figures from finished runs
    python recipes/paper_tables.py --algos cql --envs lqr_exp1 --overrides baselines.cql.with_lagrange=true \
        --out results/paper_tables_cql_lagrange       # a variant's cells and budget check, every run overridden

The default envs are the paper's three LQR experiments, ``lqr_nondiag`` (an LQR system not in the paper, with
coupled dynamics and control: ``configs/env/lqr_nondiag.yaml``) and MountainCar. The table budget is
``table`` in ``configs/study_budgets.yaml`` (the same for every algorithm: 2×128 networks and 2,000 steps, evaluated
every 500 steps for the learning curves, CQL with 4 random actions per state; ``--quick``: ``table_quick``).
Everything else is ``configs/wbrm_offline.yaml``. The algorithms are the registry's (``torchrl_wbrm.algos.ALGOS``).

Then the budget check (``--budget-envs``, default ``lqr_exp1``; ``--budget-steps``, default 1,000 and 4,000): those
envs' cells again at other step budgets, each its own runs on the same data and seeds, into
``<out>_budget_check/steps<N>``. Every optimiser's learning rate is annealed over ``q.steps``, so a curve inside one
run always improves at its end; whether the table's budget suffices shows only against runs of a larger one
(:func:`budget_table`, ``budget_check.png``).

Every (env, algorithm, seed) runs through the studies' shared runner (``run_cells`` in ``recipes/studies/runs.py``: an
(env, algorithm)'s seeds in one local process, ``--jobs`` of them at a time, or a Hydra launcher with ``--launcher``)
into ``<out>/<env>/<algo>/seed<seed>``; every algorithm sees the same data for a given seed, collected once into a
``data_cache``. Then the report (``recipes/studies/paper_tables_report.py``) writes ``tables.md`` and the figures from
the finished runs.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

from studies.paper_tables_report import budget_check_dir, report

#: the run directory of a cell: <out>/<env>/<algo>/seed<seed>
LABELS = ("env", "method")
#: the paper's LQR experiments 1-3, an LQR system not in the paper, and MountainCar
DEFAULT_ENVS = ["lqr_exp1", "lqr_exp2", "lqr_exp3", "lqr_nondiag", "mountain_car"]

#: the budget check: the grid's runs of these envs again at these step budgets (each evaluated once, at its end, on
#: the same data and seeds), beside the grid's own runs at the table budget. A learning curve read inside one run
#: cannot tell whether a budget suffices: every optimiser's learning rate is annealed to 0 over ``q.steps`` (cosine),
#: so the last stretch of any budget improves; only runs of a larger budget can.
BUDGET_CHECK_ENVS = ["lqr_exp1"]
BUDGET_CHECK_STEPS = [1000, 4000]


def available_algos() -> list[str]:
    from torchrl_wbrm.algos import algo_names

    return sorted(algo_names())


def build_cells(envs: list[str], algos: list[str], out: Path, quick: bool, overrides=()) -> list[dict]:
    """One cell per (env, algorithm); every cell of an env and seed shares one data collection (``data_cache``).
    ``overrides`` (``--overrides``) go last on every cell, e.g. ``baselines.cql.with_lagrange=true``."""
    cells = []
    for env in envs:
        extra = []
        if env == "mountain_car":  # the paper's 100 evaluation episodes (2 in the smoke version); 5 at training time
            extra = [f"eval.episodes={2 if quick else 100}", f"eval.train_episodes={1 if quick else 5}"]
        for algo in algos:
            cells.append({"env": env, "method": algo, "overrides": [
                f"env={env}", f"algo={algo}", "logger=none", "plots=false", "checkpoint_every=0",
                f"data_cache={out / 'data_cache'}", *extra, *overrides]})
    return cells


def build_budget_cells(envs: list[str], algos: list[str], out: Path, quick: bool, steps: int,
                       overrides=()) -> list[dict]:
    """The grid's cells of ``envs`` at a budget of ``steps`` Q steps, evaluated once at the end; they read the grid's
    ``data_cache``, so every budget of a seed trains on the same data."""
    cells = build_cells(envs, algos, out, quick, overrides)
    for cell in cells:
        cell["overrides"] = [*cell["overrides"], f"q.steps={steps}", f"q.eval_every={steps}"]
    return cells


def _unfinished(cells: list[dict], seeds, out: Path) -> int:
    """How many of the (cell, seed) runs under ``out`` have no ``results.json`` yet."""
    from studies.runs import cell_dir

    return sum(not (cell_dir(out, cell, seed, labels=LABELS) / "results.json").is_file()
               for cell in cells for seed in seeds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algos", nargs="+", default=None, help=f"default: every registered algo ({available_algos()})")
    parser.add_argument("--envs", nargs="+", default=DEFAULT_ENVS)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--jobs", type=int, default=2, help="parallel local processes, one per (env, algorithm) "
                        "and its seeds")
    parser.add_argument("--launcher", default=None,
                        help="a Hydra launcher instead of local processes: submitit_local, submitit_slurm, ray "
                             "(pip install -e '.[sweeps]')")
    parser.add_argument("--launcher-args", nargs="*", default=[],
                        help="launcher overrides, e.g. hydra.launcher.partition=cpu hydra.launcher.timeout_min=30")
    parser.add_argument("--budget-envs", nargs="*", default=BUDGET_CHECK_ENVS,
                        help="the envs of the budget check (none: skip it); only those also in --envs run")
    parser.add_argument("--budget-steps", nargs="+", type=int, default=None,
                        help=f"the budget check's q.steps (default {BUDGET_CHECK_STEPS}; --quick: 5 20)")
    parser.add_argument("--overrides", nargs="*", default=[], metavar="KEY=VALUE",
                        help="recipe overrides for every run, after the table budget, e.g. "
                             "baselines.cql.with_lagrange=true (use an --out of their own: the tables read every "
                             "run there)")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--out", default=None,
                        help="where the runs and tables go (default results/paper_tables; --quick: results/paper_tables_quick)")
    parser.add_argument("--report-only", action="store_true",
                        help="only rebuild tables.md and the figures from finished runs")
    from studies.docs_fragments import add_docs_dir_argument, budget_text, docs_dir_from_args, \
        publish_study

    add_docs_dir_argument(parser)
    args = parser.parse_args()
    out = Path(args.out or ("results/paper_tables_quick" if args.quick else "results/paper_tables"))  # a smoke run never mixes with the full one
    algos = args.algos or available_algos()
    unknown = sorted(set(algos) - set(available_algos()))
    if unknown:
        raise SystemExit(f"Unknown algorithms {unknown}: choose from {available_algos()} (torchrl_wbrm/algos/).")
    if not args.report_only:
        from torchrl_wbrm.training.results import write_json
        from studies.runs import run_cells, study_budget

        os.environ.setdefault("MPLBACKEND", "Agg")
        seeds = range(1 if args.quick else args.seeds)
        budget = study_budget("table_quick" if args.quick else "table")
        launch = dict(jobs=args.jobs, labels=LABELS, launcher=args.launcher, launcher_args=args.launcher_args)
        timing_path = out / "wall_seconds.json"
        timing = json.loads(timing_path.read_text()) if timing_path.is_file() else {}
        cells = build_cells(args.envs, algos, out, args.quick, args.overrides)
        todo = _unfinished(cells, seeds, out)
        start = time.perf_counter()
        run_cells(cells, seeds, budget, out, **launch)
        if todo:  # a call that only finds finished runs keeps the time of the call that ran them
            timing.update(wall_seconds=time.perf_counter() - start, envs=args.envs, algos=algos, seeds=args.seeds)
        check_envs = [e for e in args.envs if e in (args.budget_envs or [])]
        start, todo = time.perf_counter(), 0
        for steps in (args.budget_steps or ([5, 20] if args.quick else BUDGET_CHECK_STEPS)) if check_envs else []:
            cells, where = build_budget_cells(check_envs, algos, out, args.quick, steps, args.overrides), \
                budget_check_dir(out) / f"steps{steps}"
            todo += _unfinished(cells, seeds, where)
            run_cells(cells, seeds, budget, where, **launch)
        if todo:
            timing.update(budget_check_seconds=time.perf_counter() - start, budget_envs=check_envs)
        write_json(timing_path, timing)
    from torchrl_wbrm.training.reporting import load_results

    text, figures = report(out)
    print(text)
    from studies.runs import study_budget

    name = "table_quick" if args.quick else "table"
    steps = args.budget_steps or ([5, 20] if args.quick else BUDGET_CHECK_STEPS)
    publish_study("paper_tables", out / "tables.md", docs_dir_from_args(args.docs_dir, args.quick),
                  seeds={r["seed"] for r in load_results(out) if "seed" in r}, figures=figures,
                  budget=budget_text(name, study_budget(name)) + "; the budget check: "
                  + ", ".join(f"`q.steps={s}`" for s in steps) + f" on {', '.join(args.budget_envs or []) or 'no env'}")
    from torchrl_wbrm.training.logging import log_study_summary  # the group's wandb summary run (offline)

    log_study_summary("paper_tables", out, tables=[out / "tables.md"], figures=[f for f in figures if f is not None])


if __name__ == "__main__":
    main()
