"""Write (or check) the recipe output that the README and the tutorials show, by running the commands they show.

    python docs/example_outputs.py                      # every example: run it, write docs/run_outputs/<name>.txt
    python docs/example_outputs.py minari_cartpole      # one example
    python docs/example_outputs.py --check              # run them and compare with what the pages show

Each example is a list of commands exactly as a page shows them (``python ...``, run in a fresh temporary directory,
``recipes/`` read from this clone). What the last command prints is kept: its standard output, then the Python
warnings it wrote to standard error (as ``UserWarning: <message>``, without the file and line that raised it); the
tqdm bars are left out. Two things of the machine are written as placeholders: the temporary directory (paths are
relative to it) and the date in a run directory's name (``<date>``). The pages include ``docs/run_outputs/<name>.txt``
(the README holds a copy between ``<!-- example-output: <name> -->`` markers, rewritten here too), so what a page
shows is what its command printed.

``--check`` compares a fresh run with the file line by line: the same lines with every number replaced by ``#``, and
each number within 0.1% (or 0.003) of the one shown, except on the ``wall time`` line, which depends on the machine.
``tests/test_docs_outputs.py`` runs the same check.
"""
from __future__ import annotations

import argparse
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
OUTPUTS = ROOT / "docs" / "run_outputs"


@dataclass(frozen=True)
class Example:
    """Commands as a page shows them, and the pages that show the last one's output."""

    commands: tuple[str, ...]
    pages: tuple[str, ...]
    #: (a file of the last command's run directory, where the pages show it), copied by a write
    figures: tuple[tuple[str, str], ...] = ()


_MINARI_DATA = "python -m torchrl_wbrm.data.minari_examples --env {env} --data-path datasets/minari"
_MINARI_RUN = ("python recipes/wbrm_offline.py env=minari env.minari.expert=examples/{env}/expert-v0 "
               "env.minari.behaviour=examples/{env}/behaviour-v0 env.minari.data_path=datasets/minari")

#: name -> the commands a page shows; their output goes to docs/run_outputs/<name>.txt
EXAMPLES: dict[str, Example] = {
    "lqr_default": Example(("python recipes/wbrm_offline.py",), ("README.md", "docs/tutorials/lqr.md"),
                           (("evaluation.png", "docs/img/default_exp1_evaluation.png"),
                            ("training_curve.png", "docs/img/default_exp1_training_curve.png"))),
    "minari_mountain_car": Example(
        (_MINARI_DATA.format(env="mountain_car"), _MINARI_RUN.format(env="mountain_car") + " q.bc_alpha=2.5 threads=1"),
        ("docs/tutorials/minari.md",), (("evaluation.png", "docs/img/minari_mountain_car_evaluation.png"),)),
    "minari_cartpole": Example(
        (_MINARI_DATA.format(env="cartpole"), _MINARI_RUN.format(env="cartpole") + " seed=0"),
        ("docs/tutorials/minari.md",)),
}

#: runs ``argv`` (``python`` already resolved) in ``cwd`` and returns the completed process
Runner = Callable[[list, Path, dict], subprocess.CompletedProcess]

_WARNING = re.compile(r"^\S.*?:\d+: (\w*Warning): (.*)$")
_NUMBER = re.compile(r"-?\d+(?:[.,]\d+)*(?:e[+-]?\d+)?")
_DATE = re.compile(r"\d{4}-\d\d-\d\d_\d\d-\d\d-\d\d")


def argv_of(command: str) -> list[str]:
    """``python <script or -m module> <args>`` as the argument list this clone runs it with."""
    words = shlex.split(command)
    if words[0] != "python":
        raise ValueError(f"an example command starts with 'python': {command!r}")
    if words[1].endswith(".py"):
        words[1] = str(ROOT / words[1])
    return [sys.executable, *words[1:]]


def _subprocess(argv: list, cwd: Path, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True)


def printed(stdout: str, stderr: str, workdir: Path) -> str:
    """What a page shows of a run: standard output, then the Python warnings of standard error, the machine's
    temporary directory and dates made placeholders."""
    lines = [line for line in stdout.splitlines() if "generated new fontManager" not in line]  # matplotlib's first run
    for line in stderr.replace("\r", "\n").splitlines():
        match = _WARNING.match(line)
        if match:
            lines.append(f"{match.group(1)}: {match.group(2)}")
    text = "\n".join(lines).strip() + "\n"
    for prefix in {str(workdir), str(Path(workdir).resolve())}:
        text = text.replace(prefix + os.sep, "")
    return _DATE.sub("<date>", text)


def run_directory(output: str, workdir: Path) -> Path:
    """The run directory that the output's ``run directory: <path>`` line names (its date a placeholder)."""
    match = re.search(r"^run directory: (.+)$", output, re.M)
    if not match:
        raise ValueError(f"no 'run directory:' line in the output:\n{output}")
    found = sorted(Path(workdir).glob(match.group(1).strip().replace("<date>", "*")))
    if len(found) != 1:
        raise ValueError(f"{match.group(1)!r} matches {len(found)} directories under {workdir}")
    return found[0]


def run_example(name: str, workdir: Path, runner: Runner = _subprocess) -> str:
    """Run the example's commands in ``workdir`` (one thread, no dashboard) and return what its last one printed."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg", "WANDB_MODE": "disabled"}
    proc = None
    for command in EXAMPLES[name].commands:
        proc = runner(argv_of(command), Path(workdir), env)
        if proc.returncode != 0:
            raise RuntimeError(f"{name}: {command!r} exited with {proc.returncode}:\n{proc.stderr[-3000:]}")
    return printed(proc.stdout, proc.stderr, Path(workdir))


def differences(shown: str, fresh: str) -> list[str]:
    """How ``fresh`` differs from ``shown``: lines of another form, or numbers more than 0.1% (or 0.003) apart (not on
    the ``wall time`` line). Empty when the page is up to date."""
    want, have = shown.strip().splitlines(), fresh.strip().splitlines()
    problems = []
    if len(want) != len(have):
        problems.append(f"{len(want)} lines shown, {len(have)} printed")
    for a, b in zip(want, have):
        if _NUMBER.sub("#", a) != _NUMBER.sub("#", b):
            problems.append(f"shown:   {a}\nprinted: {b}")
        elif not a.startswith("wall time"):
            for x, y in zip(_NUMBER.findall(a), _NUMBER.findall(b)):
                x, y = float(x.replace(",", "")), float(y.replace(",", ""))
                if abs(x - y) > max(3e-3, 1e-3 * abs(x)):
                    problems.append(f"shown:   {a}\nprinted: {b}")
                    break
    return problems


def readme_block(name: str, text: str) -> re.Match | None:
    """The README's copy of an example's output, between ``<!-- example-output: <name> -->`` markers."""
    return re.search(rf"<!-- example-output: {name} -->\n```\n(.*?)```\n<!-- /example-output -->", text, re.S)


def write(name: str, output: str, workdir: Path) -> None:
    """The output to docs/run_outputs/<name>.txt and the README's copy; the run's figures to where the pages show them."""
    run_dir = run_directory(output, workdir) if EXAMPLES[name].figures else None
    for source, target in EXAMPLES[name].figures:
        shutil.copyfile(run_dir / source, ROOT / target)
    (OUTPUTS / f"{name}.txt").write_text(output)
    for page in EXAMPLES[name].pages:
        path = ROOT / page
        text = path.read_text()
        block = readme_block(name, text)
        if block:
            path.write_text(text[:block.start(1)] + output + text[block.end(1):])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("names", nargs="*", metavar="NAME",
                        help=f"examples to run (default: all of {', '.join(EXAMPLES)})")
    parser.add_argument("--check", action="store_true", help="compare with docs/run_outputs/ instead of writing it")
    args = parser.parse_args(argv)
    unknown = [name for name in args.names if name not in EXAMPLES]
    if unknown:
        parser.error(f"unknown example {unknown[0]!r}: one of {', '.join(EXAMPLES)}")
    failed = 0
    for name in args.names or list(EXAMPLES):
        start = time.perf_counter()
        with tempfile.TemporaryDirectory(prefix=f"example_{name}_") as workdir:
            output = run_example(name, Path(workdir))
            seconds = time.perf_counter() - start
            if args.check:
                problems = differences((OUTPUTS / f"{name}.txt").read_text(), output)
                failed += bool(problems)
                print(f"{name}: {'stale' if problems else 'up to date'} ({seconds:.0f} s)", *problems, sep="\n",
                      flush=True)
            else:
                write(name, output, Path(workdir))
                print(f"{name}: wrote docs/run_outputs/{name}.txt and its figures ({seconds:.0f} s)", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
