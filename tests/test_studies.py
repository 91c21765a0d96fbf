"""The studies' ``--quick`` versions (CI), and the runner's local path (a cell's seeds in one process) on a tiny LQR
config. The weighting study runs in a subprocess, as a user launches it; the others run in the test process with one
job (tests/inprocess.py: the cells train here one after another, and no worker process imports torch again).

Apart from ``tests/test_recipes.py`` (the main recipe's smoke runs) so that ``--dist loadfile`` can put the two
files' minutes of runs on different workers."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from tests.inprocess import run_script
from tests.references import ROOT

pytestmark = pytest.mark.slow  # each test runs a study, or trains

#: the tiny LQR config (tests/references.py) as study overrides, after the ``quick`` study budget
TINY_BUDGET = [
    "env.lqr_data.behaviour_episodes=40", "env.lqr_data.expert_episodes=20", "env.lqr_data.parallel_envs=20",
    "ratio.steps=30", "ratio.batch_size=64", "ratio.eval_every=10", "ratio.num_cells=[16,16]",
    "q.steps=40", "q.batch_size=32", "q.eval_every=20", "q.num_cells=[16,16]", "q.actor_num_cells=[16,16]",
    "eval.offline_value=false", "eval.episodes=50", "eval.train_episodes=20", "eval.q_samples=300",
]


def run_study(script: str, *args: str, timeout: int = 300) -> subprocess.CompletedProcess:
    """Run ``recipes/<script> --quick <args>`` as a user would; fail with its output's tail if it fails."""
    proc = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / script), "--quick", *args],
        cwd=ROOT, capture_output=True, text=True, timeout=timeout,
        env={**os.environ, "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1"},
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    return proc


def run_study_here(script: str, *args: str) -> subprocess.CompletedProcess:
    """``python recipes/<script> --quick --jobs 1 <args>`` in this process, without the study's wandb summary run
    (``WANDB_MODE=disabled``; tests/test_wandb.py checks that run); fail with its output's tail if it fails."""
    proc = run_script(ROOT / "recipes" / script, "--quick", "--jobs", "1", *args,
                      env={**os.environ, "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1", "WANDB_MODE": "disabled"})
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    return proc


def test_weighting_study_quick(tmp_path):
    """The cheapest quick study with a figure, also with ``--docs-dir``: its docs fragment is its ``tables.md`` under
    a header naming the command, and its figure is copied (a quick run writes no fragment without ``--docs-dir``)."""
    from studies.docs_fragments import read_fragment

    docs = tmp_path / "docs"
    run_study("weighting_study.py", "--jobs", "1", "--out", str(tmp_path), "--first-seed", "3", "--docs-dir", str(docs))
    runs = sorted(p.parent.name for p in tmp_path.rglob("results.json"))
    assert runs and set(runs) == {"seed3"}, runs  # --first-seed 3: the one quick seed is seed 3, not seed 0
    tables = (tmp_path / "tables.md").read_text()
    assert "unweighted" in tables and "learned ŵ (paper)" in tables and "select" in tables
    assert (tmp_path / "weighting_study.png").is_file()
    command, details, body = read_fragment((docs / "results" / "_generated" / "weighting_study.md").read_text())
    assert body == tables
    assert command == (f"python recipes/weighting_study.py --quick --jobs 1 --out {tmp_path} --first-seed 3 "
                       f"--docs-dir {docs}")
    assert details.startswith("Seeds: 1 (3). Budget: `quick` in configs/study_budgets.yaml (`env.lqr_data.")
    assert details.endswith("±: a 95% Student-t interval over seeds.")
    assert (docs / "img" / "weighting_study.png").read_bytes() == (tmp_path / "weighting_study.png").read_bytes()


#: the quick paper tables' algorithms: one of each kind the tables tell apart (WBRM: the ratio, a held-out Bellman
#: residual and Q̂'s error; BC: no Q; DQN: a discrete action grid). Every registered algorithm runs through the
#: recipe with its figures in tests/test_baselines.py; a run of all ten here cost about 29 s of CPU, 10 s with three.
TABLE_ALGOS = ("wbrm", "bc", "dqn")


def test_paper_tables_quick(tmp_path):
    """``--quick`` on an LQR env and MountainCar with three algorithms (the budget check at one other budget, 20
    steps, on lqr_exp1)."""
    run_study_here("paper_tables.py", "--envs", "lqr_exp1", "mountain_car", "--algos", *TABLE_ALGOS,
                   "--budget-steps", "20", "--out", str(tmp_path))
    algos = set(TABLE_ALGOS)
    finished = {(p.parents[1].parent.name, p.parents[1].name) for p in tmp_path.glob("*/*/seed0/results.json")}
    assert finished == {(env, a) for env in ("lqr_exp1", "mountain_car") for a in algos}
    checked = {p.parents[1].name for p in (tmp_path.parent / f"{tmp_path.name}_budget_check" / "steps20").glob(
        "lqr_exp1/*/seed0/results.json")}
    assert checked == algos
    tables = (tmp_path / "tables.md").read_text()
    assert "Table 2 (LQR)" in tables and "Table 3 (MountainCarContinuous-v0)" in tables
    assert all(f"| {a} |" in tables for a in algos) and "85.435" in tables  # the exact optimum row
    assert len(list((tmp_path / "data_cache").iterdir())) == 2  # one collection per env and seed, shared
    assert (tmp_path / "paper_tables.png").is_file() and (tmp_path / "wall_seconds.json").is_file()
    assert "### Cost" in tables and "### Budget check" in tables
    # the learning curves: two Q evaluations per quick run (the table_quick study budget), a row per (env, algorithm)
    assert (tmp_path / "learning_curves.png").is_file() and "### Budget and convergence" in tables
    assert "| lqr_exp1 | dqn | regret | 10 | 2 |" in tables and "| mountain_car | dqn | return | 10 | 2 |" in tables


def test_ablations_quick(tmp_path):
    run_study_here("ablations.py", "--out", str(tmp_path))
    tables = (tmp_path / "tables.md").read_text()
    # the default run appears in every block; the KL setting in its own; BRM beside WBRM for behaviour noise
    for block in ("residual x bootstrap", "ratio divergence", "expert noise τ", "expert data size m", "behaviour noise"):
        assert f"### {block} (LQR exp1)" in tables
    assert "| KL (α → 0) | wbrm | 1 |" in tables and "| σ_b=0.5 (default) | brm | 1 |" in tables
    assert len(list(tmp_path.rglob("results.json"))) == 3  # default wbrm, default brm, KL: the default ran once


# ---------------------------------------------------------------------- the runner: a cell's seeds in one process
def _cell(method: str = "wbrm") -> dict:
    return {"block": "b", "env": "lqr_exp1", "setting": "s", "method": method,
            "overrides": ["env=lqr_exp1", f"algo={method}"]}


def test_a_cells_seeds_train_as_one_job_with_a_separate_runs_figures(tmp_path, monkeypatch):
    """Locally, ``run_cells`` trains a cell's seeds as one ``run_seeds`` job: each seed's ``results.json`` is where
    ``cell_dir`` says, with the cell's labels and its share of the job's wall time, and holds the final figures of a
    separate run with that seed (within the evaluation's 95% CI); the job's combined results are ``seeds.json``, so
    ``load_results`` reads each seed once. A rerun skips the finished seeds (a new one runs alone), and refuses
    finished seeds of another config."""
    from torchrl_wbrm.training import seeds as seeds_module
    from torchrl_wbrm.training.reporting import load_results
    from studies.runs import SEEDS_RECORD, _overrides, cell_dir, run_cells, run_overrides, study_budget

    jobs = []
    run_seeds = seeds_module.run_seeds

    def counted(cfg, run_dir, **kwargs):
        jobs.append((list(cfg.seeds), run_dir))
        return run_seeds(cfg, run_dir, **kwargs)

    monkeypatch.setattr(seeds_module, "run_seeds", counted)
    cell, budget, out = _cell(), [*study_budget("quick"), *TINY_BUDGET], tmp_path / "study"
    run_cells([cell], [0, 1], budget, out, jobs=1)
    parent = cell_dir(out, cell, 0).parent
    assert jobs == [([0, 1], parent)]  # one job for the cell's two seeds
    assert not (parent / "results.json").exists()
    record = json.loads((parent / SEEDS_RECORD).read_text())
    assert record["kind"] == "seeds" and record["seeds"] == [0, 1]
    labels = {"block": "b", "env": "lqr_exp1", "setting": "s", "method": "wbrm"}
    for seed in (0, 1):
        results = json.loads((cell_dir(out, cell, seed) / "results.json").read_text())
        assert results["seed"] == seed and results["study"] == labels and results["status"] == "finished"
        assert results["job"]["seeds"] == [0, 1]
        assert results["wall_seconds"] == pytest.approx(results["job"]["wall_seconds"] / 2)
        alone = run_overrides(_overrides(cell, seed, budget), tmp_path / "alone" / f"seed{seed}")
        for key in ("regret", "return"):
            assert abs(results["final"][key] - alone["final"][key]) <= alone["final"][f"{key}_ci"], (seed, key)
        assert results["final"]["q_error_expert"] == pytest.approx(alone["final"]["q_error_expert"], rel=0.05)
    records = load_results(out)
    assert sorted(r["seed"] for r in records) == [0, 1] and all(r["study"] == labels for r in records)
    assert len(list(out.rglob("results.json"))) == 2

    before = {s: (cell_dir(out, cell, s) / "results.json").read_text() for s in (0, 1)}
    run_cells([cell], [0, 1, 2], budget, out, jobs=1)  # seeds 0 and 1 are finished; seed 2 runs alone
    assert len(jobs) == 1
    assert {s: (cell_dir(out, cell, s) / "results.json").read_text() for s in (0, 1)} == before
    third = json.loads((cell_dir(out, cell, 2) / "results.json").read_text())
    assert third["seed"] == 2 and third["study"] == labels and "job" not in third
    with pytest.raises(ValueError, match=r"q\.steps: 40 -> 41.*another directory"):
        run_cells([cell], [0, 1], [*budget, "q.steps=41"], out, jobs=1)


def test_a_cells_seeds_are_split_into_the_job_and_single_runs(tmp_path, monkeypatch):
    """Which of a cell's seeds the job trains: not the finished ones, nor one with a checkpoint (an interrupted single
    run, resumed on its own), nor a lone unfinished seed (a single run, which checkpoints)."""
    from studies import runs
    from torchrl_wbrm.training.config import config_as_dict

    cell, budget, out = _cell("brm"), [*runs.study_budget("quick"), "q.steps=7"], tmp_path
    done = runs.cell_dir(out, cell, 1)
    done.mkdir(parents=True)
    config = config_as_dict(runs.compose_recipe_config(runs._overrides(cell, 1, budget)))
    (done / "results.json").write_text(json.dumps({"status": "finished", "config": config}))
    runs.cell_dir(out, cell, 0).mkdir(parents=True)
    (runs.cell_dir(out, cell, 0) / "checkpoint.pt").write_bytes(b"")
    calls = []
    monkeypatch.setattr(runs, "run_cell", lambda cell, seed, *args: calls.append(("alone", seed)))
    monkeypatch.setattr(runs, "_run_seeds_job", lambda cell, seeds, *args: calls.append(("job", seeds)))
    runs.run_cell_seeds(cell, [0, 1, 2, 3], budget, out)
    assert calls == [("alone", 0), ("job", [2, 3])]
    calls.clear()
    runs.run_cell_seeds(cell, [1, 2], budget, out)
    assert calls == [("alone", 2)]


def test_a_seed_finished_by_a_stopped_job_gets_its_cells_labels_and_is_reported(tmp_path, monkeypatch):
    """A job killed after its first seed leaves that seed's results without the cell's labels (the job writes them at
    its end): running the cell again skips the seed and labels it, so the reports count it."""
    from studies import runs
    from torchrl_wbrm.training.config import config_as_dict
    from torchrl_wbrm.training.reporting import load_results

    cell, budget, out = _cell("brm"), [*runs.study_budget("quick"), "q.steps=7"], tmp_path
    done = runs.cell_dir(out, cell, 0)
    done.mkdir(parents=True)
    config = config_as_dict(runs.compose_recipe_config(runs._overrides(cell, 0, budget)))
    (done / "results.json").write_text(json.dumps({"status": "finished", "seed": 0, "config": config,
                                                   "final": {"normalised_score": 1.0}}))
    assert [r.get("study") for r in load_results(out)] == [None]
    monkeypatch.setattr(runs, "run_cell", lambda *args: pytest.fail("a finished seed ran again"))
    runs.run_cell_seeds(cell, [0], budget, out)
    labelled = json.loads((done / "results.json").read_text())
    assert labelled["study"] == {k: cell[k] for k in runs.LABELS} and labelled["final"] == {"normalised_score": 1.0}
    assert [r["study"] for r in load_results(out)] == [labelled["study"]]
