"""Aggregate the results.json files of a sweep into a Markdown table (mean ± 95% CI over seeds).

Only finished runs enter the table; diverged (or otherwise unfinished) runs are listed and counted, and runs
flagged for a Q̂ blow-up are listed and counted in the table's ``flagged`` column.

    python recipes/summarise.py multirun/wbrm_offline/<date> --group-by q.residual q.bootstrap ratio.source
"""
from __future__ import annotations

import argparse

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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("root")
    parser.add_argument("--group-by", nargs="+", default=["env.name", "ratio.source"])
    parser.add_argument("--digits", type=int, default=4)
    args = parser.parse_args()
    records = load_results(args.root)
    finished, other = split_by_status(records)
    metrics = LQR_METRICS if any("regret" in r.get("final", {}) for r in records) else MC_METRICS
    print(f"{len(records)} runs under {args.root}: {len(finished)} finished, {len(other)} not finished (excluded).")
    for r in other:
        d = r.get("diverged", {})
        print(f"  excluded ({r.get('status')}): {r.get('_path')}"
              + (f"  stage {d.get('stage')!r} step {d.get('step')} {d.get('figure')} = {d.get('value')}" if d else ""))
    for r in finished:
        if r.get("flags"):
            scale = r.get("q_scale", {})
            print(f"  flagged {', '.join(r['flags'])}: {r.get('_path')}  |{scale.get('figure')}| = "
                  f"{scale.get('max_abs_q_mean')} > {scale.get('factor')} x r_max/(1 - gamma) = {scale.get('bound')}")
    if not finished:
        print("No finished runs: no table.")
        return
    print(results_table(finished, args.group_by, metrics, digits=args.digits))


if __name__ == "__main__":
    main()
