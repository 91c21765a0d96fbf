"""A study's tables and figures as the docs show them: ``docs/results/_generated/<page>.md`` and ``docs/img/``.

Each results page of the Sphinx site includes its study's fragment; the study writes it when it runs, so the page
shows exactly what the command produced. A fragment is the study's ``tables.md`` (or ``convergence.md``) after a
three-line header:

.. code-block:: text

    The tables below are written by `python recipes/ablations.py`; running it again regenerates them.

    Seeds: 5 (0–4). Budget: `table` in configs/study_budgets.yaml (...). ±: a 95% Student-t interval over seeds.

    | ... the tables, as the study wrote them ... |

The first line names the command (the script relative to the repository, then its arguments as given); the third
the seeds, the budget and the kind of interval. :func:`read_fragment` splits a fragment back into the two.

A study calls :func:`publish_study` at its end with the docs folder :func:`docs_dir_from_args` resolves from its
``--docs-dir`` option (:func:`add_docs_dir_argument`): by default the clone's ``docs/`` for a full study and none
for ``--quick`` or for an installed package.
"""
from __future__ import annotations

import argparse
import os
import re
import shlex
import shutil
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path

__all__ = ["CI_OVER_SEEDS", "FIRST_LINE", "add_docs_dir_argument", "budget_text", "command_line", "default_docs_dir",
           "docs_dir_from_args", "fragment_header", "publish_study", "read_fragment", "seeds_text"]

#: The kind of interval of most studies' tables.
CI_OVER_SEEDS = "a 95% Student-t interval over seeds"
#: A fragment's first line: the command that writes it.
FIRST_LINE = re.compile(r"^The tables below are written by `(?P<command>python [^`]+)`; running it again regenerates "
                        r"them\.$")
_ROOT = Path(__file__).resolve().parents[2]


def default_docs_dir() -> Path | None:
    """The repository's ``docs/`` when the package runs from a clone (``docs/conf.py`` beside ``pyproject.toml``
    above the package), else ``None`` (an installed package has no docs to write)."""
    docs = _ROOT / "docs"
    return docs if (docs / "conf.py").is_file() and (_ROOT / "pyproject.toml").is_file() else None


def add_docs_dir_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--docs-dir PATH`` (``none``: write no fragment) to a study's parser."""
    parser.add_argument(
        "--docs-dir", default=None, metavar="PATH",
        help="the Sphinx docs folder that receives the tables (results/_generated/<page>.md) and the figures (img/); "
             "default: the clone's docs/ for a full study, none for --quick or an installed package; 'none': skip")


def docs_dir_from_args(docs_dir: str | os.PathLike | None, quick: bool = False) -> Path | None:
    """The folder ``--docs-dir`` names: ``none`` → ``None``; unset → :func:`default_docs_dir` for a full study,
    ``None`` for ``quick``."""
    if docs_dir is None:
        return None if quick else default_docs_dir()
    return None if str(docs_dir).lower() == "none" else Path(docs_dir)


def command_line(argv: Sequence[str] | None = None) -> str:
    """``python <script> <args>``: the command that is running (``sys.argv``), its script relative to the repository
    when it lies in it."""
    argv = list(sys.argv if argv is None else argv)
    script = Path(argv[0])
    try:
        script = script.resolve().relative_to(_ROOT)
    except ValueError:
        pass
    return "python " + shlex.join([script.as_posix(), *argv[1:]])


def seeds_text(seeds: Iterable[int] | str) -> str:
    """``5 (0–4)`` for ``range(5)``, ``3 (10, 12, 14)`` for others; a string is kept as it is."""
    if isinstance(seeds, str):
        return seeds
    seeds = sorted(int(s) for s in seeds)
    if not seeds:
        return "none"
    if seeds == list(range(seeds[0], seeds[-1] + 1)):
        span = str(seeds[0]) if len(seeds) == 1 else f"{seeds[0]}–{seeds[-1]}"
    else:
        span = ", ".join(map(str, seeds))
    return f"{len(seeds)} ({span})"


def fragment_header(command: str, seeds: Iterable[int] | str, budget: str, ci: str = CI_OVER_SEEDS) -> str:
    """The three lines above a fragment's tables (a blank line between): the command, then seeds, budget and CI."""
    first = f"The tables below are written by `{command}`; running it again regenerates them."
    assert FIRST_LINE.match(first), first  # a command holding a backtick would not render
    return f"{first}\n\nSeeds: {seeds_text(seeds)}. Budget: {budget}. ±: {ci}.\n\n"


def budget_text(name: str | None, overrides: Sequence[str] = ()) -> str:
    """``\\`name\\` in configs/study_budgets.yaml (\\`a\\`, \\`b\\`)``: a study budget and its overrides."""
    listed = ", ".join(f"`{o}`" for o in overrides)
    if name is None:
        return listed or "the recipe's defaults"
    return f"`{name}` in configs/study_budgets.yaml" + (f" ({listed})" if listed else "")


def read_fragment(text: str) -> tuple[str, str, str]:
    """``(command, details, tables)`` of a fragment's text; ``ValueError`` when it has not the header's format."""
    lines = text.split("\n", 4)
    match = FIRST_LINE.match(lines[0])
    if len(lines) < 5 or not match or lines[1] or lines[3] or not lines[2].startswith("Seeds: "):
        raise ValueError("not a study's docs fragment (its first line names the command that writes it, its third "
                         "the seeds, budget and interval): " + text[:200])
    return match["command"], lines[2], lines[4]


def publish_study(page: str, tables: str | os.PathLike, docs_dir: str | os.PathLike | None, *,
                  seeds: Iterable[int] | str, budget: str, budget_overrides: Sequence[str] = (),
                  figures: Iterable[str | os.PathLike | None] = (), ci: str = CI_OVER_SEEDS,
                  argv: Sequence[str] | None = None) -> Path | None:
    """Write ``<docs_dir>/results/_generated/<page>.md`` (the header and the text of the file ``tables``, unchanged)
    and copy each of ``figures`` that exists into ``<docs_dir>/img/``. Returns the fragment's path; ``None`` (and
    nothing written) when ``docs_dir`` is ``None``.

    ``budget``: a study budget's name in ``configs/study_budgets.yaml`` (its ``budget_overrides`` listed after it)
    or, with no overrides, a description as it is; ``argv``: the command (default ``sys.argv``).
    """
    if docs_dir is None:
        return None
    docs_dir = Path(docs_dir)
    budget = budget_text(budget, budget_overrides) if budget_overrides else budget
    fragment = docs_dir / "results" / "_generated" / f"{page}.md"
    fragment.parent.mkdir(parents=True, exist_ok=True)
    fragment.write_text(fragment_header(command_line(argv), seeds, budget, ci) + Path(tables).read_text())
    img = docs_dir / "img"
    for figure in figures:
        if figure is not None and Path(figure).is_file():
            img.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(figure, img / Path(figure).name)
    print(f"docs: wrote {fragment}")
    return fragment
