"""The linter runs in CI: ``ruff check torchrl_wbrm recipes examples benchmarks tests`` (settings in pyproject.toml) finds
nothing."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_ruff_finds_nothing():
    proc = subprocess.run([sys.executable, "-m", "ruff", "check", "torchrl_wbrm", "recipes", "examples", "benchmarks", "tests"], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert "No module named ruff" not in proc.stderr, "ruff is a dev dependency: pip install -e '.[dev]'"
    assert proc.returncode == 0, proc.stdout + proc.stderr
