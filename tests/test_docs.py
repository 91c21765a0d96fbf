"""The Sphinx site in docs/ builds with warnings as errors, and its doctests pass (what CI runs); every results page
includes its study's generated fragment, and every figure it shows exists."""
from __future__ import annotations

import re
import subprocess
import sys

import pytest

from tests.references import ROOT

DOCS = ROOT / "docs"


def _sphinx(builder: str, out) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", builder, str(DOCS), str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=600,
                          env={**__import__("os").environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"})


@pytest.fixture(scope="module")
def sphinx():
    pytest.importorskip("sphinx", reason="sphinx is not installed: pip install -e '.[docs]' (the dev extra has it)")
    pytest.importorskip("myst_parser", reason="myst-parser is not installed: pip install -e '.[docs]'")


def test_the_site_builds_without_warnings(sphinx, tmp_path):
    result = _sphinx("html", tmp_path / "html")
    assert result.returncode == 0, result.stderr[-4000:]
    assert (tmp_path / "html" / "index.html").is_file()
    assert (tmp_path / "html" / "method.html").is_file()


def test_the_doctests_pass(sphinx, tmp_path):
    result = _sphinx("doctest", tmp_path / "doctest")
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-4000:]
    assert re.search(r"[1-9]\d* tests?", (tmp_path / "doctest" / "output.txt").read_text())


STUDIES = ["paper_tables", "weighting_study", "q_accuracy_study", "ablations", "convergence", "benchmark",
           "peer_d3rlpy"]


@pytest.mark.parametrize("study", STUDIES)
def test_each_results_page_includes_its_studys_fragment(study):
    page = (DOCS / "results" / f"{study}.md").read_text()
    assert f"```{{include}} _generated/{study}.md" in page
    fragment = (DOCS / "results" / "_generated" / f"{study}.md").read_text()
    assert fragment.count("\n|") >= 3, fragment[:200]


def test_every_image_the_docs_and_readme_show_exists():
    for path in [ROOT / "README.md", *DOCS.rglob("*.md")]:
        if "_build" in path.parts:
            continue
        for target in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", path.read_text()):
            assert (path.parent / target).is_file(), (path, target)


def test_no_project_history_in_the_readme_or_the_docs():
    """No commit hashes, dates, "round" or issue numbers: the README and the docs describe the project as it is."""
    for path in [ROOT / "README.md", *DOCS.rglob("*.md")]:
        if "_build" in path.parts or "_autosummary" in path.parts:
            continue
        text = path.read_text()
        assert not re.search(r"\b(this|last|previous|next) round\b|\bround's\b", text, re.I), path
        assert not re.search(r"\bissue \d+|\b20\d\d-\d\d-\d\d\b|\b\d{1,2} (January|February|March|April|May|June|July|"
                             r"August|September|October|November|December) 20\d\d\b", text), path
        assert not re.search(r"\bcommit `?[0-9a-f]{7,40}\b|\bat `?[0-9a-f]{7}`?\b", text), path
