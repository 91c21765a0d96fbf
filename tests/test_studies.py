"""The studies' ``--quick`` versions (CI), each in a subprocess as a user would launch it.

Apart from ``tests/test_recipes.py`` (the main recipe's smoke runs) so that ``--dist loadfile`` can put the two
files' minutes of subprocess runs on different workers."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tests.references import ROOT

pytestmark = pytest.mark.slow  # each test runs a study in a subprocess


def run_study(script: str, *args: str, timeout: int = 300) -> subprocess.CompletedProcess:
    """Run ``recipes/<script> --quick <args>`` as a user would; fail with its output's tail if it fails."""
    proc = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / script), "--quick", *args],
        cwd=ROOT, capture_output=True, text=True, timeout=timeout,
        env={**os.environ, "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1"},
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    return proc


def test_weighting_study_quick(tmp_path):
    """The cheapest quick study with a figure, also with ``--docs-dir``: its docs fragment is its ``tables.md`` under
    a header naming the command, and its figure is copied (a quick run writes no fragment without ``--docs-dir``)."""
    from torchrl_wbrm.training.docs_fragments import read_fragment

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


def test_paper_tables_quick(tmp_path):
    """``--quick`` with its default algorithms: every registered one, on an LQR env and MountainCar (the budget check
    at one other budget, 20 steps, on lqr_exp1)."""
    from torchrl_wbrm.algos import algo_names

    run_study("paper_tables.py", "--envs", "lqr_exp1", "mountain_car", "--budget-steps", "20", "--out", str(tmp_path),
              timeout=900)
    algos = algo_names()
    finished = {(p.parents[1].parent.name, p.parents[1].name) for p in tmp_path.glob("*/*/seed0/results.json")}
    assert len(algos) >= 10 and finished == {(env, a) for env in ("lqr_exp1", "mountain_car") for a in algos}
    checked = {p.parents[1].name for p in (tmp_path.parent / f"{tmp_path.name}_budget_check" / "steps20").glob(
        "lqr_exp1/*/seed0/results.json")}
    assert checked == set(algos)
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
    run_study("ablations.py", "--jobs", "1", "--out", str(tmp_path))
    tables = (tmp_path / "tables.md").read_text()
    # the default run appears in every block; the KL setting in its own; BRM beside WBRM for behaviour noise
    for block in ("residual x bootstrap", "ratio divergence", "expert noise τ", "expert data size m", "behaviour noise"):
        assert f"### {block} (LQR exp1)" in tables
    assert "| KL (α → 0) | wbrm | 1 |" in tables and "| σ_b=0.5 (default) | brm | 1 |" in tables
    assert len(list(tmp_path.rglob("results.json"))) == 3  # default wbrm, default brm, KL: the default ran once
