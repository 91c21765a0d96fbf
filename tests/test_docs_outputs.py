"""The recipe output that the README and the tutorials show is what their commands print (docs/example_outputs.py).

The pages include ``docs/run_outputs/<name>.txt`` (the README holds a copy between markers); no page types a recipe's
output by hand; each page shows the commands that wrote it; and, in the slow tests, the commands run again as a user
types them (a fresh ``python``, a fresh directory) and print the lines shown, each figure within rounding.
"""
from __future__ import annotations

import ast
import importlib.util
import os
import re
import subprocess
import sys

import pytest

from tests.references import ROOT

_spec = importlib.util.spec_from_file_location("docs_example_outputs", ROOT / "docs" / "example_outputs.py")
example_outputs = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = example_outputs  # dataclasses look their module up by name
_spec.loader.exec_module(example_outputs)

EXAMPLES = example_outputs.EXAMPLES
OUTPUTS = ROOT / "docs" / "run_outputs"

#: the first line the recipe prints at the end of a run, ``env <name>  seed <n>  algo <algo>``
_SUMMARY = re.compile(r"^```[a-z]*\n(env \S+  seed \d+  algo .*?)^```", re.S | re.M)


def _pages():
    return [ROOT / "README.md", *(p for p in (ROOT / "docs").rglob("*.md") if "_build" not in p.parts)]


def _commands(page_text: str) -> set[str]:
    """Every command of the page's ``bash`` blocks: continuation lines joined, comments dropped, ``&&`` split,
    spaces collapsed."""
    commands = set()
    for block in re.findall(r"^```bash\n(.*?)^```", page_text, re.S | re.M):
        for line in block.replace("\\\n", " ").splitlines():
            for command in re.split(r"&&|;", re.sub(r"\s+#.*$", "", line)):
                commands.add(" ".join(command.split()))
    return commands


def test_each_example_has_its_output_file_and_no_other_file_is_there():
    assert sorted(p.stem for p in OUTPUTS.glob("*.txt")) == sorted(EXAMPLES)
    for name in EXAMPLES:
        text = (OUTPUTS / f"{name}.txt").read_text()
        assert text.startswith("env ") and "\nwall time " in text, (name, text[:200])


def test_no_page_types_a_recipe_output_by_hand():
    """A block that starts like the recipe's summary is only the README's marked copy of an output file."""
    for page in _pages():
        text = page.read_text()
        for block in _SUMMARY.findall(text):
            copies = [name for name in EXAMPLES if (OUTPUTS / f"{name}.txt").read_text() == block]
            assert copies, f"{page.relative_to(ROOT)} shows a recipe output that no example wrote:\n{block}"
            assert page.name == "README.md" and example_outputs.readme_block(copies[0], text), page


@pytest.mark.parametrize("name", list(EXAMPLES))
def test_each_page_shows_the_examples_output_and_the_commands_that_printed_it(name):
    output = (OUTPUTS / f"{name}.txt").read_text()
    for page in EXAMPLES[name].pages:
        path = ROOT / page
        text = path.read_text()
        if path.name == "README.md":
            block = example_outputs.readme_block(name, text)
            assert block and block.group(1) == output, f"README.md's copy of {name} differs from docs/run_outputs/"
        else:
            include = re.search(rf"^```{{literalinclude}} (\S+/run_outputs/{name}\.txt)$", text, re.M)
            assert include and (path.parent / include.group(1)).resolve() == OUTPUTS / f"{name}.txt", (page, name)
        missing = [c for c in EXAMPLES[name].commands if c not in _commands(text)]
        assert not missing, f"{page} does not show the command(s) {missing} of {name}"


def test_a_flag_or_warning_the_text_names_is_in_the_output_it_shows():
    """A page's text may explain a ``FLAG`` line or a warning of an output it includes only if the output has it."""
    for page in {p for example in EXAMPLES.values() for p in example.pages}:
        text = (ROOT / page).read_text()
        shown = "".join((OUTPUTS / f"{name}.txt").read_text() for name in EXAMPLES if page in EXAMPLES[name].pages)
        prose = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
        for named in re.findall(r"FLAG \w+|\b\w*Warning\b", prose):
            assert named in shown, f"{page} names {named!r}, which no output it shows has"


def test_a_stale_output_is_told_apart_from_a_fresh_one():
    """The check: every line's form, every figure within 0.1% (or 0.003), the wall time free; a missing or an extra
    line (a FLAG the page lacks) is stale."""
    shown = "return 476.17 ± 6.54 over the evaluation episodes\nESS 527 (33.77%)\nwall time 415.6 s (data 1.0 s)\n"
    assert example_outputs.differences(shown, shown.replace("415.6 s (data 1.0", "76.0 s (data 0.0")) == []
    assert example_outputs.differences(shown, shown.replace("476.17", "476.18")) == []  # rounding
    assert example_outputs.differences(shown, shown.replace("476.17", "500.00"))
    assert example_outputs.differences(shown, shown.replace("33.77", "33.97"))
    assert example_outputs.differences(shown, shown.replace("ESS", "ESS over D"))
    assert example_outputs.differences(shown, shown + "FLAG ratio_collapse: stage 1 failed\n")
    assert example_outputs.differences(shown, shown.split("\n", 1)[1])


def test_what_a_run_printed_is_kept_without_the_machine(tmp_path):
    """Standard output, then the warnings (type and message) of standard error, tqdm bars and matplotlib's cache
    note left out; the temporary directory and the run's date made placeholders."""
    stdout = (f"[2026-01-01 10:00:00,000][HYDRA] generated new fontManager\nenv minari  seed 0  algo wbrm\n"
              f"run directory: {tmp_path}/outputs/wbrm_offline/minari/2026-01-02_03-04-05_seed0\n")
    stderr = ("stage 1: 100%|█████| 10/10 [00:01<00:00]\r/x/y.py:651: UserWarning: Q is diverging.\n"
              "  self._watch_q_bound(q_value, tensordict)\n")
    assert example_outputs.printed(stdout, stderr, tmp_path) == (
        "env minari  seed 0  algo wbrm\nrun directory: outputs/wbrm_offline/minari/<date>_seed0\n"
        "UserWarning: Q is diverging.\n")


def test_the_writer_refuses_a_command_it_cannot_run_as_shown():
    with pytest.raises(ValueError, match="starts with 'python'"):
        example_outputs.argv_of("wbrm-offline env=minari")
    argv = example_outputs.argv_of("python recipes/wbrm_offline.py seed=0")
    assert argv[1] == str(ROOT / "recipes" / "wbrm_offline.py") and argv[2:] == ["seed=0"]


@pytest.mark.slow
@pytest.mark.parametrize("name", list(EXAMPLES))
def test_the_shown_output_is_what_the_commands_print(name, tmp_path):
    """The example's commands, run as shown in a fresh directory, print what the pages show (the wall time apart).
    The LQR default costs about 45 s of CPU, each Minari run about 85 s."""
    fresh = example_outputs.run_example(name, tmp_path)
    problems = example_outputs.differences((OUTPUTS / f"{name}.txt").read_text(), fresh)
    assert not problems, (f"docs/run_outputs/{name}.txt is stale: run `python docs/example_outputs.py {name}`\n"
                          + "\n".join(problems))


def test_the_readme_says_how_its_sample_output_and_its_headline_differ():
    """The sample output is one seed at the recipe's defaults, the headline the mean over seeds at the tables'
    budget: the README says so with the budgets that the recipe and configs/study_budgets.yaml hold, and its
    headline's WBRM row is the paper-tables fragment's."""
    from torchrl_wbrm.tasks import LQRTask
    from studies.runs import study_budget
    from tests.references import compose_recipe

    readme = (ROOT / "README.md").read_text()
    width = compose_recipe().q.num_cells
    steps = LQRTask.TRAINING_DEFAULTS.q.steps
    defaults = f"one run, seed 0, at the recipe's defaults ({len(width)}×{width[0]} networks, {steps:,} steps)"
    assert defaults in readme.lower().replace("\n", " "), defaults
    table = dict(override.split("=", 1) for override in study_budget("table"))
    cells = ast.literal_eval(table["q.num_cells"])
    budget = f"({len(cells)}×{cells[0]} networks, {int(table['q.steps']):,} steps"
    headline = readme[readme.index("## Results"):].replace("\n", " ")
    assert f"the mean over seeds 0–4 at the baselines' shared budget {budget}" in headline, budget
    fragment = (ROOT / "docs" / "results" / "_generated" / "paper_tables.md").read_text()
    wbrm = re.search(r"^\| wbrm \| ([^|]+) \|", fragment, re.M).group(1).strip()
    assert f"| WBRM (`algo=wbrm`) | {wbrm} |" in readme, wbrm
    assert "Seeds: 5 (0–4)." in fragment


@pytest.mark.slow
def test_the_dataset_tables_the_few_demonstrations_page_shows_are_what_the_benchmark_command_prints(tmp_path):
    """The page shows the benchmark command's per-dataset table for Pendulum and LunarLander "as the command prints
    it": the command (``python -m torchrl_wbrm.data.benchmark --tasks pendulum lunar_lander``, data written under
    the test's own directory) prints each of those rows, and the page shows each row it prints. About 60 s of CPU."""
    page = (ROOT / "docs" / "results" / "few_demonstrations.md").read_text()
    assert "Pendulum-v1, as the command prints it:" in page and "the same command with `--tasks lunar_lander`" in page
    pattern = r"^\| benchmark/(?:pendulum|lunar_lander)/[\w-]+ \|.*\|$"
    shown = re.findall(pattern, page, re.M)
    assert len(shown) == 14, shown
    argv = example_outputs.argv_of(
        f"python -m torchrl_wbrm.data.benchmark --data-path {tmp_path / 'data'} --tasks pendulum lunar_lander")
    proc = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    printed = re.findall(pattern, proc.stdout, re.M)
    assert sorted(printed) == sorted(shown), "\n".join(sorted(set(printed) ^ set(shown)))
