"""Mutation check: does the test suite catch a deliberately broken method?

    python tools/mutation_check.py                 # every mutation, each against its own subset of the suite
    python tools/mutation_check.py --only drop_weights skip_restore
    python tools/mutation_check.py --full          # each mutation against the whole suite (-x; much slower)
    python tools/mutation_check.py --list
    python tools/mutation_check.py --dry-run       # apply each mutation to a copy and count the lines it changes

For each breakage in :data:`MUTATIONS` it copies the working tree to a temporary directory, applies the one change
there (each equation and each step is implemented once, so a mutation replaces a fragment found exactly once),
runs the chosen tests in the copy (the copy's package is imported: ``PYTHONPATH`` and the working directory point at
it, which the script checks) and reports *caught* (the tests fail) or *NOT CAUGHT*. First it runs every subset on an
unmodified copy: a subset that fails without a mutation would "catch" anything, so the check stops there.

Not part of CI (it runs the suite's learning tests several times). Exit status 0 only if every mutation was caught.
Runs torch with one thread (``OMP_NUM_THREADS=1``), one test process at a time.
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
IGNORE = shutil.ignore_patterns(
    ".git", ".venv", "outputs", "multirun", "results", "__pycache__", ".pytest_cache", "*.egg-info", "wandb"
)


@dataclass
class Mutation:
    """One breakage: in ``path``, the fragment ``old``, found there exactly once, becomes ``new``."""

    name: str
    what: str
    path: str
    old: str
    new: str
    tests: list[str]
    changed: int = field(default=0, init=False)


LEARNING = "tests/test_baselines.py::test_each_method_beats_the_behaviour_policy_in_regret"
Q_LEARNING = "tests/test_baselines.py::test_each_q_method_estimates_q_star_better_than_the_baselines"

MUTATIONS = [
    Mutation(
        "drop_weights", "stage 2 ignores ŵ: the residual is weighted by ones",
        "torchrl_wbrm/objectives/weighted_bellman.py",
        "            weight,\n            residual=self.residual,", "            torch.ones_like(weight),\n            residual=self.residual,",
        ["tests/test_weighted_bellman.py"],
    ),
    Mutation(
        "ignore_target", "the bootstrap reads the online Q even with delay_value=True",
        "torchrl_wbrm/objectives/weighted_bellman.py",
        "params = self.target_value_network_params if self.delay_value else self.value_network_params",
        "params = self.value_network_params",
        ["tests/test_weighted_bellman.py", "tests/test_mabo.py"],
    ),
    Mutation(
        "flip_gamma", "the trainer discounts with −γ",
        "torchrl_wbrm/training/parts.py",
        "gamma = task.gamma(cfg.q.gamma)", "gamma = -task.gamma(cfg.q.gamma)",
        ["tests/test_baselines.py::test_each_algo_discounts_with_the_env_gamma_and_reads_its_data"],
    ),
    Mutation(
        "gamma_half", "the trainer discounts with γ = 0.5 instead of the env's 0.9",
        "torchrl_wbrm/training/parts.py",
        "gamma = task.gamma(cfg.q.gamma)", "gamma = 0.5",
        ["tests/test_baselines.py::test_each_algo_discounts_with_the_env_gamma_and_reads_its_data"],
    ),
    Mutation(
        "skip_restore", "stage 1 keeps its last state, not the best held-out one",
        "torchrl_wbrm/ratio/fitting.py",
        'self.network.load_state_dict(self.best["state"])', "pass",
        ["tests/test_training.py::test_early_stopping_stops_the_ratio_stage_and_restores_its_best_state"],
    ),
    Mutation(
        "swap_ratio", "the exact ratio is behaviour over expert",
        "torchrl_wbrm/policies/lqr.py",
        "_base(env), e.gain, e.noise_std, b.gain, b.noise_std,", "_base(env), b.gain, b.noise_std, e.gain, e.noise_std,",
        ["tests/test_training.py::test_exact_source_stores_the_true_ratio_expert_over_behaviour"],
    ),
    Mutation(
        "skip_optimiser_step", "no optimiser step in the algos' shared descent step",
        "torchrl_wbrm/algos/base.py",
        "    loss.backward()\n    if grad_clip:", "    loss.backward()\n    return\n    if grad_clip:",
        [f"{LEARNING}[wbrm]", f"{LEARNING}[brm]"],
    ),
    Mutation(
        "break_done_mask", "bootstrap through terminations (the mask 1 − terminated is dropped)",
        "torchrl_wbrm/objectives/functional.py",
        "return reward + gamma * (~terminated).int() * next_value", "return reward + gamma * next_value",
        ["tests/test_weighted_bellman.py"],
    ),
    # ---------------------------------------------------------------- added here
    Mutation(
        "store_ones", "the trainer stores w ≡ 1 over D instead of the stage-1 ŵ",
        "torchrl_wbrm/ratio/storing.py",
        "        target.set(key, w)\n", "        target.set(key, torch.ones_like(w))\n",
        ["tests/test_training.py"],
    ),
    Mutation(
        "skip_ratio_step", "stage 1 never steps its optimiser",
        "torchrl_wbrm/ratio/fitting.py",
        "        self.optimizer.step()\n", "        pass\n",
        ["tests/test_training.py::test_early_stopping_stops_the_ratio_stage_and_restores_its_best_state"],
    ),
    Mutation(
        "frozen_target", "the Bellman family never updates its target (SoftUpdate skipped)",
        "torchrl_wbrm/algos/base.py",
        "            if updater is not None and not every_step:", "            if False:",
        [f"{LEARNING}[wbrm]", f"{Q_LEARNING}[wbrm]", f"{LEARNING}[brm]", f"{Q_LEARNING}[brm]"],
    ),
    Mutation(
        "no_actor_step", "the actor (the max over actions) is never trained",
        "torchrl_wbrm/algos/base.py",
        "        if i % qc.actor_delay == 0 and loss.has_actor:", "        if False:",
        [f"{LEARNING}[wbrm]", f"{LEARNING}[brm]"],
    ),
    # ---------------------------------------------------------------- the seeds in one process
    Mutation(
        "seeds_one_seed", "seeds=[...] trains every seed with the first seed's data and initialisation",
        "torchrl_wbrm/training/config.py",
        "config.seed, config.seeds = int(seed), None", "config.seed, config.seeds = int(self.config.seeds[0]), None",
        ["tests/test_seeds.py::test_recipe_seeds_equal_separate_runs"],
    ),
    Mutation(
        "aggregate_one_seed", "the seeds' aggregate is the first seed's figures alone",
        "torchrl_wbrm/training/seeds.py",
        'values = [r["final"].get(key) for r in finished]', 'values = [r["final"].get(key) for r in finished[:1]]',
        ["tests/test_seeds.py::test_recipe_seeds_equal_separate_runs"],
    ),
]


def copy_tree(dest: Path) -> Path:
    shutil.copytree(ROOT, dest, ignore=IGNORE, symlinks=True)
    return dest


def apply(mutation: Mutation, tree: Path) -> None:
    path = tree / mutation.path
    text = path.read_text()
    found = text.count(mutation.old)
    if found != 1:
        raise SystemExit(
            f"mutation {mutation.name}: its fragment is in {mutation.path} {found} times, not once; update MUTATIONS "
            "(or implement the mutated code in one place)."
        )
    mutation.changed = len(mutation.old.rstrip("\n").splitlines())
    path.write_text(text.replace(mutation.old, mutation.new))


def run_tests(tree: Path, tests: list[str], *, full: bool, timeout: int) -> tuple[int, str, float]:
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg", "WANDB_MODE": "offline"}
    args = [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", "-W", "ignore"]
    args += [] if full else tests
    start = time.perf_counter()
    try:
        proc = subprocess.run(args, cwd=tree, env=env, capture_output=True, text=True, timeout=timeout)
        out, rc = proc.stdout + proc.stderr, proc.returncode
    except subprocess.TimeoutExpired as err:
        out, rc = f"timed out after {timeout} s\n{err.stdout or ''}", -1
    return rc, out, time.perf_counter() - start


def first_failure(output: str) -> str:
    """The first failing test and the first line of its error (pytest's ``E   ...``), so a reader can tell a caught
    mutation (an assertion about the method) from a crash."""
    lines = output.splitlines()
    test = next((re.sub(r"\s+-\s.*", "", line.split(" ", 1)[1]) for line in lines
                 if line.startswith(("FAILED", "ERROR"))), None)
    error = next((line[1:].strip() for line in lines if line.startswith("E ")), "")
    if test is None:
        return lines[-1][:110] if lines else "?"
    return f"{test[:110]}: {error[:150]}" if error else test[:110]


def check_import(tree: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    where = subprocess.run([sys.executable, "-c", "import torchrl_wbrm; print(torchrl_wbrm.__file__)"], cwd=tree,
                           env=env, capture_output=True, text=True, check=True).stdout.strip()
    if not Path(where).resolve().is_relative_to(tree.resolve()):
        raise SystemExit(f"The copy imports torchrl_wbrm from {where}, not from {tree}: the check would test nothing.")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", nargs="*", help="mutation names (default: all)")
    parser.add_argument("--full", action="store_true", help="run the whole suite (-x) for every mutation")
    parser.add_argument("--no-baseline", action="store_true", help="skip the unmutated run of the subsets")
    parser.add_argument("--timeout", type=int, default=900, help="seconds per pytest run")
    parser.add_argument("--list", action="store_true")
    parser.add_argument("--dry-run", action="store_true", help="apply each mutation to a copy, report lines, run nothing")
    args = parser.parse_args()
    chosen = [m for m in MUTATIONS if not args.only or m.name in args.only]
    if args.list:
        for m in chosen:
            print(f"{m.name:20s} {m.path}: {m.what}\n{'':20s} tests: {' '.join(m.tests)}")
        return 0
    unknown = set(args.only or ()) - {m.name for m in MUTATIONS}
    if unknown:
        raise SystemExit(f"unknown mutation(s) {sorted(unknown)}; --list shows them")
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="mutation_check_") as scratch:
        scratch = Path(scratch)
        clean = copy_tree(scratch / "clean")
        check_import(clean)
        if args.dry_run:
            for m in chosen:
                tree = scratch / m.name
                shutil.copytree(clean, tree, symlinks=True)
                apply(m, tree)
                print(f"{m.name:20s} one place, {m.changed} line(s), changed in {m.path}")
                shutil.rmtree(tree)
            return 0
        if not args.no_baseline:
            subsets = list(dict.fromkeys(t for m in chosen for t in m.tests))
            rc, out, seconds = run_tests(clean, subsets, full=args.full, timeout=args.timeout)
            print(f"unmutated copy: {'passes' if rc == 0 else 'FAILS'} ({seconds:.0f} s)", flush=True)
            if rc != 0:
                print(out[-3000:])
                raise SystemExit("The tests fail without a mutation; fix them first.")
        rows = []
        for m in chosen:
            tree = scratch / m.name
            shutil.copytree(clean, tree, symlinks=True)
            apply(m, tree)
            rc, out, seconds = run_tests(tree, m.tests, full=args.full, timeout=args.timeout)
            caught = rc != 0
            rows.append((m, caught, seconds, first_failure(out) if caught else ""))
            print(f"{m.name:20s} {'caught' if caught else 'NOT CAUGHT'} ({seconds:.0f} s) {rows[-1][3]}", flush=True)
            shutil.rmtree(tree)
    print("\n| mutation | what it breaks | lines | tests run | result | first failing test |")
    print("|---|---|---|---|---|---|")
    for m, caught, seconds, failing in rows:
        tests = "whole suite (-x)" if args.full else ", ".join(t.replace("tests/", "") for t in m.tests)
        print(f"| `{m.name}` | {m.what} (`{m.path}`) | {m.changed} | {tests} | "
              f"{'caught' if caught else '**NOT CAUGHT**'} ({seconds:.0f} s) | {failing} |")
    missed = [m.name for m, caught, _, _ in rows if not caught]
    print(f"\n{len(rows) - len(missed)} of {len(rows)} caught in {time.perf_counter() - started:.0f} s"
          + (f"; not caught: {', '.join(missed)}" if missed else ""))
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
