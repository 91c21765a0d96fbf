"""The studies' ``--quick`` versions (CI), each in a subprocess as a user would launch it.

Apart from ``tests/test_recipes.py`` (the main recipe's smoke runs) so that ``--dist loadfile`` can put the two
files' minutes of subprocess runs on different workers."""
from __future__ import annotations

import os
import subprocess
import sys

from tests.references import ROOT


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
    run_study("weighting_study.py", "--jobs", "1", "--out", str(tmp_path), "--first-seed", "3")
    runs = sorted(p.parent.name for p in tmp_path.rglob("results.json"))
    assert runs and set(runs) == {"seed3"}, runs  # --first-seed 3: the one quick seed is seed 3, not seed 0
    tables = (tmp_path / "tables.md").read_text()
    assert "unweighted" in tables and "learned ŵ (paper)" in tables and "select" in tables
    assert (tmp_path / "weighting_study.png").is_file()


def test_paper_tables_quick(tmp_path):
    run_study("paper_tables.py", "--algos", "wbrm", "td3bc", "--envs", "lqr_exp1", "mountain_car", "--out", str(tmp_path),
              timeout=600)
    tables = (tmp_path / "tables.md").read_text()
    assert "Table 2 (LQR)" in tables and "Table 3 (MountainCarContinuous-v0)" in tables
    assert "| td3bc |" in tables and "| wbrm |" in tables and "85.435" in tables  # the exact optimum row
    assert len(list((tmp_path / "data_cache").iterdir())) == 2  # one collection per env and seed, shared
    assert (tmp_path / "paper_tables.png").is_file() and (tmp_path / "wall_seconds.json").is_file()
    assert "| brm |" not in tables and "### Cost" in tables
    # the learning curves: two Q evaluations per quick run (TABLE_QUICK_BUDGET), a row per (env, algorithm)
    assert (tmp_path / "learning_curves.png").is_file() and "### Budget and convergence" in tables
    assert "| lqr_exp1 | td3bc | regret | 10 | 2 |" in tables and "| mountain_car | wbrm | return | 10 | 2 |" in tables
    # the budget check: lqr_exp1 again at 5 and 20 steps, beside the grid (its runs not in the grid's tables)
    check = tmp_path.with_name(tmp_path.name + "_budget_check")
    assert sorted(p.name for p in check.iterdir()) == ["steps20", "steps5"]
    assert "### Budget check" in tables and "| 5 steps | 10 steps (table) | 20 steps |" in tables
    assert "| lqr_exp1 | wbrm | regret |" in tables.split("### Budget check")[1]
    assert "mountain_car" not in tables.split("### Budget check")[1].split("Seeds:")[0]


def test_ablations_quick(tmp_path):
    run_study("ablations.py", "--jobs", "1", "--out", str(tmp_path))
    tables = (tmp_path / "tables.md").read_text()
    # the default run appears in every block; the KL setting in its own; BRM beside WBRM for behaviour noise
    for block in ("residual x bootstrap", "ratio divergence", "expert noise τ", "expert data size m", "behaviour noise"):
        assert f"### {block} (LQR exp1)" in tables
    assert "| KL (α → 0) | wbrm | 1 |" in tables and "| σ_b=0.5 (default) | brm | 1 |" in tables
    assert len(list(tmp_path.rglob("results.json"))) == 3  # default wbrm, default brm, KL: the default ran once
