"""``recipes/misspecified_study.py --quick`` in a subprocess, as a user launches it: its files and their shape."""
from __future__ import annotations

import csv
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_misspecified_study_quick(tmp_path):
    out = tmp_path / "study"
    proc = subprocess.run([sys.executable, str(ROOT / "recipes" / "misspecified_study.py"), "--quick", "--out",
                           str(out), "--docs-dir", "none"], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    rows = list(csv.DictReader(open(out / "results.csv")))
    assert len(rows) == 2 * 2 * 3  # behaviours × classes (quick: poly2, mlp8) × weightings
    assert {r["weighting"] for r in rows} == {"uniform", "learned ŵ", "exact w"}
    assert all(math.isfinite(float(r["q_error"])) and math.isfinite(float(r["value_error"])) for r in rows)
    assert all(math.isfinite(float(r["regret"])) for r in rows if r["class"] == "poly2")
    tables = (out / "tables.md").read_text()
    assert "### Behaviour near" in tables and "### Behaviour far" in tables and "Paired differences" in tables
    assert (out / "misspecified_q.png").stat().st_size > 10_000
    assert not (tmp_path / "docs").exists()  # --docs-dir none writes no fragment
