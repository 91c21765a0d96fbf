"""Does a change leave the recipe's figures unchanged? Same seed, same figures: runs the recipe's trainer in this
process and compares its final figures with a saved run's, digit for digit.

    python benchmarks/same_figures.py --save /tmp/before.json                 # before the change
    python benchmarks/same_figures.py --against /tmp/before.json              # after it: equal, or what moved
    python benchmarks/same_figures.py --save /tmp/before.json env=lqr_exp2 q.steps=3000   # any recipe override

Without overrides it runs a shortened default recipe (ratio 300, Q 600 steps, one thread); ``--against`` reruns with
the overrides saved in the file. Exit status 1 when a figure differs.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

#: The shortened default recipe, one thread (a run's figures depend on the thread count).
DEFAULT_OVERRIDES = ["ratio.steps=300", "q.steps=600", "q.eval_every=300", "threads=1"]
#: The final figures compared.
FIGURES = ("regret", "return", "q_error_expert", "q_error_behaviour", "held_out_bellman_residual")


def run(overrides: list[str]) -> dict:
    """The final figures of the recipe's trainer with ``overrides`` (no logger, no plots)."""
    from hydra import compose, initialize_config_dir

    from torchrl_wbrm.configs import CONFIG_DIR
    from torchrl_wbrm.training import WBRMTrainer, register_configs

    register_configs()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("wbrm_offline", overrides=["logger=none", "plots=false", *overrides])
    with tempfile.TemporaryDirectory() as tmp:
        final = WBRMTrainer(cfg, Path(tmp) / "run", progress=False).run()["final"]
    return {k: final[k] for k in FIGURES if k in final}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--save", type=Path, help="write this run's figures (and its overrides) to this JSON file")
    group.add_argument("--against", type=Path, help="compare this run's figures with those saved in this file")
    parser.add_argument("overrides", nargs="*", help="recipe overrides (default: a shortened default recipe)")
    args = parser.parse_args(argv)
    if args.against is not None:
        saved = json.loads(args.against.read_text())
        overrides = args.overrides or saved["overrides"]
    else:
        overrides = args.overrides or DEFAULT_OVERRIDES
    figures = run(overrides)
    print(f"final figures ({' '.join(overrides)}):")
    print("  " + "  ".join(f"{k} {v!r}" for k, v in figures.items()))
    if args.save is not None:
        args.save.write_text(json.dumps({"overrides": overrides, "figures": figures}, indent=1))
        print(f"saved to {args.save}")
        return 0
    if overrides != saved["overrides"]:
        print(f"  note: the saved run had the overrides {' '.join(saved['overrides'])}")
    moved = {k: (saved["figures"].get(k), v) for k, v in figures.items() if saved["figures"].get(k) != v}
    if not moved:
        print(f"  the same figures as {args.against}, digit for digit")
        return 0
    for k, (before, now) in moved.items():
        print(f"  {k}: {before!r} -> {now!r}")
    return 1


if __name__ == "__main__":
    os.environ.setdefault("TQDM_DISABLE", "1")
    sys.exit(main())
