"""Aggregate the results.json files of a sweep into a Markdown table (mean ± 95% CI over seeds).

Only finished runs enter the table; diverged (or otherwise unfinished) runs are listed and counted, and flagged
runs (``q_blow_up``, ``below_behaviour``, ``return_fell``, ...) are listed and counted in the table's ``flagged``
column. Minari runs get the normalised score as well; ``--per-seed`` lists one metric seed by seed.

    python recipes/summarise.py multirun/wbrm_offline/<date> --group-by q.residual q.bootstrap ratio.source
    python recipes/summarise.py <run dir> --group-by algo q.steps --digits 1 --per-seed "normalised score"
"""
from __future__ import annotations

import argparse
import sys

from torchrl_wbrm.training.reporting import load_results, results_table, split_by_status

LQR_METRICS = {
    "paired regret": "final.regret",
    "Q̂ error / spread (expert)": "final.q_error_expert",
    "Q̂ bias (expert)": "final.q_bias_expert",
    "Q̂ bias (behaviour)": "final.q_bias_behaviour",
    "return": "final.return",
    "ESS of weights": "weights.ess",
}
MC_METRICS = {"return": "final.return"}
#: Minari runs: the D4RL-normalised score as well (0 = random actions, 100 = the expert)
MINARI_METRICS = {"normalised score": "final.normalised_score", "return": "final.return"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("root")
    parser.add_argument("--group-by", nargs="+", default=["env.name", "ratio.source"])
    parser.add_argument("--digits", type=int, default=4)
    parser.add_argument("--per-seed", metavar="METRIC", default=None,
                        help="also list this metric's value seed by seed (with the step delivered by q.select and "
                             "the run's flags), e.g. 'normalised score'")
    args = parser.parse_args()
    try:
        records = load_results(args.root)
    except (ValueError, FileNotFoundError, OSError) as err:  # a damaged results.json, none at all: one line
        print(f"summarise: {' '.join(str(err).split())}", file=sys.stderr)
        sys.exit(2)
    finished, other = split_by_status(records)
    if any("regret" in r.get("final", {}) for r in records):
        metrics = LQR_METRICS
    elif any("normalised_score" in r.get("final", {}) for r in records):
        metrics = MINARI_METRICS
    else:
        metrics = MC_METRICS
    if args.per_seed is not None and args.per_seed not in metrics:
        parser.error(f"--per-seed {args.per_seed!r}: choose one of these runs' metrics {sorted(metrics)}")
    print(f"{len(records)} runs under {args.root}: {len(finished)} finished, {len(other)} not finished (excluded).")
    for r in other:
        d = r.get("diverged", {})
        print(f"  excluded ({r.get('status')}): {r.get('_path')}"
              + (f"  stage {d.get('stage')!r} step {d.get('step')} {d.get('figure')} = {d.get('value')}" if d else ""))
    for r in finished:
        if r.get("flags"):
            line = f"  flagged {', '.join(r['flags'])}: {r.get('_path')}"
            if "q_blow_up" in r["flags"]:
                scale = r.get("q_scale", {})
                line += (f"  |{scale.get('figure')}| = {scale.get('max_abs_q_mean')} > {scale.get('factor')} x "
                         f"r_max/(1 - gamma) = {scale.get('bound')}")
            print(line)
    if not finished:
        print("No finished runs: no table.")
        return
    print(results_table(finished, args.group_by, metrics, digits=args.digits, per_seed=args.per_seed))


if __name__ == "__main__":
    main()
