"""Aggregate the results.json files of a sweep into a Markdown table (mean ± 95% CI over seeds).

    python recipes/summarise.py multirun/wbrm_offline/<date> --group-by q.residual q.bootstrap ratio.source
"""
from __future__ import annotations

import argparse

from torchrl_wbrm.training.reporting import load_results, results_table

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
    metrics = LQR_METRICS if any("regret" in r.get("final", {}) for r in records) else MC_METRICS
    print(results_table(records, args.group_by, metrics, digits=args.digits))


if __name__ == "__main__":
    main()
