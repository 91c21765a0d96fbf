"""The Sphinx site in docs/ builds with warnings as errors, and its doctests pass (what CI runs); every results page
includes its study's generated fragment, and every figure it shows exists.

The two builds run ``python -m sphinx`` in the test process (:func:`tests.inprocess.run_script`: the package is
imported already) and share one doctree directory: the doctest build reads the pages the html build has read, instead
of reading and autodoc-importing every source again. Run alone, the doctest build reads them itself."""
from __future__ import annotations

import os
import re
import sys
import warnings
from pathlib import Path

import pytest

from tests.inprocess import run_script
from tests.references import ROOT

DOCS = ROOT / "docs"


def _sphinx(builder: str, out, doctrees):
    """``python -m sphinx -W --keep-going -q -b <builder> -d <doctrees> docs <out>``, in this process."""
    import sphinx

    path = list(sys.path)  # docs/conf.py puts the repository first on it
    try:
        with warnings.catch_warnings():  # as in its own python: no deprecation warnings of the libraries
            warnings.simplefilter("ignore", DeprecationWarning)
            warnings.simplefilter("ignore", PendingDeprecationWarning)
            return run_script(Path(sphinx.__file__).parent / "__main__.py", "-W", "--keep-going", "-q", "-b", builder,
                              "-d", doctrees, DOCS, out,
                              env={**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"})
    finally:
        sys.path[:] = path


@pytest.fixture(scope="module")
def sphinx():
    pytest.importorskip("sphinx", reason="sphinx is not installed: pip install -e '.[docs]' (the dev extra has it)")
    pytest.importorskip("myst_parser", reason="myst-parser is not installed: pip install -e '.[docs]'")


@pytest.fixture(scope="module")
def doctrees(tmp_path_factory):
    """The doctree directory both builds use."""
    return tmp_path_factory.mktemp("doctrees")


def test_the_site_builds_without_warnings(sphinx, doctrees, tmp_path):
    """The site builds, and reads as a person needs it: the maths renders offline (MathJax shipped into the site, no
    script from the network), every figure links to its full-size image, and the stylesheet that wraps or scrolls
    code blocks and wide tables is loaded on every page."""
    result = _sphinx("html", tmp_path / "html", doctrees)
    assert result.returncode == 0, result.stderr[-4000:]
    html = tmp_path / "html"
    assert (html / "index.html").is_file()
    method = (html / "method.html").read_text()
    scripts = re.findall(r'<script[^>]*src="([^"]+)"', method)
    assert not [s for s in scripts if re.match(r"(https?:)?//", s)], scripts  # nothing from the network
    mathjax = [s for s in scripts if "mathjax" in s.lower()]
    assert mathjax and (html / mathjax[0].split("?")[0]).is_file(), mathjax
    assert "\\(" in method or "\\[" in method, "the method page has no maths for MathJax to render"
    shown = 0
    for page in html.rglob("*.html"):
        text = page.read_text()
        assert "_static" in page.parts or "_static/readable.css" in text, f"{page.relative_to(html)} lacks readable.css"
        for image in re.findall(r'<img [^>]*src="([^"]*_images/[^"]+)"', text):
            shown += 1
            assert re.search(rf'<a class="reference internal image-reference" href="{re.escape(image)}"><img ', text), \
                (page.relative_to(html), image)  # a click opens the full-size image
    assert shown >= len(list((DOCS / "img").glob("*.png"))), shown
    css = (DOCS / "_static" / "readable.css").read_text()
    assert re.search(r"div\.highlight pre \{\s*overflow-x: auto;", css) and "white-space: pre-wrap" in css


def test_the_doctests_pass(sphinx, doctrees, tmp_path):
    result = _sphinx("doctest", tmp_path / "doctest", doctrees)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-4000:]
    assert re.search(r"[1-9]\d* tests?", (tmp_path / "doctest" / "output.txt").read_text())


STUDIES = ["paper_tables", "weighting_study", "q_accuracy_study", "ablations", "convergence", "benchmark",
           "peer_d3rlpy", "few_demonstrations", "misspecified_q", "offline_value", "offline_value_validation",
           "locomotion", *(f"locomotion_peer_{task}" for task in ("hopper", "halfcheetah", "walker2d"))]
#: the results page of a fragment whose page is named otherwise
PAGES = {"offline_value_validation": "offline_value",
         **{study: "locomotion" for study in STUDIES if study.startswith("locomotion_peer_")}}


@pytest.mark.parametrize("study", STUDIES)
def test_each_results_page_includes_its_studys_fragment(study):
    page = (DOCS / "results" / f"{PAGES.get(study, study)}.md").read_text()
    assert f"```{{include}} _generated/{study}.md" in page
    fragment = (DOCS / "results" / "_generated" / f"{study}.md").read_text()
    assert fragment.count("\n|") >= 3, fragment[:200]


def test_every_committed_fragment_names_the_command_that_writes_it():
    """Each fragment in docs/results/_generated/ has the header :func:`publish_study` writes: its first line names
    the study's command (one of the commands its page shows), its third the seeds, the budget and the interval."""
    from studies.docs_fragments import read_fragment

    fragments = sorted((DOCS / "results" / "_generated").glob("*.md"))
    assert {p.stem for p in fragments} == set(STUDIES)
    for path in fragments:
        command, details, tables = read_fragment(path.read_text())
        script = command.split()[1]
        assert (ROOT / script).is_file() and script.startswith(("recipes/", "benchmarks/")), (path, command)
        page = DOCS / "results" / f"{PAGES.get(path.stem, path.stem)}.md"
        assert script in (DOCS / "results" / "index.md").read_text() + page.read_text()
        assert re.match(r"Seeds: \d+ .*\. Budget: .+\. ±: .+\.$", details), (path, details)
        assert tables.startswith(("|", "#")), (path, tables[:100])


def test_publish_study_writes_nothing_without_a_docs_dir(tmp_path):
    """``--docs-dir none`` and ``--quick`` without ``--docs-dir`` write nothing; a full study run from this clone
    writes into its docs/."""
    from studies.docs_fragments import default_docs_dir, docs_dir_from_args, publish_study

    assert docs_dir_from_args(None, quick=True) is None and docs_dir_from_args("none") is None
    assert docs_dir_from_args(None) == default_docs_dir() == DOCS
    assert docs_dir_from_args(str(tmp_path)) == tmp_path
    (tmp_path / "tables.md").write_text("| a |\n|---|\n| 1 |\n")
    assert publish_study("x", tmp_path / "tables.md", None, seeds=range(2), budget="b") is None
    assert not list(tmp_path.rglob("x.md"))


def test_every_image_the_docs_and_readme_show_exists():
    """Markdown images and ``{image}``/``{figure}`` directives; a page shows a figure through a directive with a size
    (``:scale:``), so that Sphinx links it to its full-size image."""
    for path in [ROOT / "README.md", *DOCS.rglob("*.md")]:
        if "_build" in path.parts:
            continue
        text = path.read_text()
        if path.name != "README.md":
            assert not re.search(r"!\[[^\]]*\]\(", text), f"{path}: show a figure with {{image}} and :scale: 100"
        for target in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text):
            assert (path.parent / target).is_file(), (path, target)
        for target, options in re.findall(r"^```\{(?:image|figure)\} (\S+)\n((?::\w+:.*\n)*)", text, re.M):
            assert (path.parent / target).is_file(), (path, target)
            assert re.search(r"^:(scale|width):", options, re.M), (path, target, "no size: no link to the full image")


def test_each_results_page_states_its_finding_first():
    """Its first lines, before any command, table or figure: a short paragraph that starts ``**Finding.**``."""
    for path in sorted((DOCS / "results").glob("*.md")):
        lines = path.read_text().splitlines()
        assert lines[0].startswith("# ") and not lines[1] and lines[2].startswith("**Finding.** "), path
        paragraph = lines[2:lines.index("", 2)]
        assert len(paragraph) <= 8 and not any(line.startswith(("|", "```", "#")) for line in paragraph), path


def test_tests_cite_findings_where_they_are():
    """An expected failure or a threshold that cites a finding names a page that exists; none cites the README,
    which holds no per-method findings."""
    for path in (ROOT / "tests").glob("test_*.py"):
        text = path.read_text()
        assert "(" + "README)" not in text, path
        for cited in re.findall(r"\b(docs/[\w/]+\.md)\b", text):
            assert (ROOT / cited).is_file(), (path, cited)


def test_no_project_history_in_the_readme_or_the_docs():
    """No commit hashes, dates, "round" or issue numbers: the README and the docs describe the project as it is, and
    no source file speaks of a development round."""
    sources = [p for folder in ("torchrl_wbrm", "recipes", "tools", "benchmarks", "examples", "tests", "configs")
               for p in (ROOT / folder).rglob("*.*") if p.suffix in (".py", ".yaml", ".md")]
    for path in sources:
        assert not re.search(r"\b(this|last|previous|next|a|one) round\b|\bround's\b|\bround \d", path.read_text(),
                             re.I), path
    for path in [ROOT / "README.md", *DOCS.rglob("*.md")]:
        if "_build" in path.parts or "_autosummary" in path.parts:
            continue
        text = path.read_text()
        assert not re.search(r"\b(this|last|previous|next) round\b|\bround's\b", text, re.I), path
        assert not re.search(r"\bissue \d+|\b20\d\d-\d\d-\d\d\b|\b\d{1,2} (January|February|March|April|May|June|July|"
                             r"August|September|October|November|December) 20\d\d\b", text), path
        assert not re.search(r"\bcommit `?[0-9a-f]{7,40}\b|\bat `?[0-9a-f]{7}`?\b", text), path


def test_the_readmes_python_api_runs_as_written(tmp_path):
    """The README's Python API block, run in a fresh directory (in this process), line for line but one: its step budget
    (``cfg.q.steps = 3000``, the default) is cut so that the test stays short. It prints the recipe's summary and
    writes the run where the README says, ``outputs/wbrm_offline/lqr_exp1/<date>_seed0``."""
    readme = (ROOT / "README.md").read_text()
    section = readme[readme.index("## The Python API"):]
    block = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    budget = "cfg.q.steps = 3000"
    assert budget in block, block
    block = block.replace(budget, "cfg.q.steps = 60; cfg.ratio.steps = 60; cfg.eval.episodes = 50")
    (tmp_path / "api.py").write_text(block)
    proc = run_script(tmp_path / "api.py", cwd=tmp_path, env={**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "env lqr_exp1  seed 0  algo wbrm" in proc.stdout and "paired regret" in proc.stdout, proc.stdout
    runs = list((tmp_path / "outputs" / "wbrm_offline" / "lqr_exp1").glob("*_seed0"))
    assert len(runs) == 1 and (runs[0] / "results.json").is_file(), runs
    assert str(runs[0].relative_to(tmp_path)) in proc.stdout.splitlines()[-1], proc.stdout


def test_the_method_page_names_every_equation_of_functional():
    """Each equation is implemented once, in ``objectives/functional.py``, and the method page links every one of them
    (and holds no control character a Python escape would have left in its LaTeX)."""
    from torchrl_wbrm.objectives import functional

    page = (DOCS / "method.md").read_text()
    missing = [name for name in functional.__all__ if name.islower() and f"functional.{name}`" not in page]
    assert missing == [], f"docs/method.md does not link {missing}"
    assert not [c for c in page if ord(c) < 32 and c != "\n"], "docs/method.md holds a control character"
