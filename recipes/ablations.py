"""Ablations of WBRM on LQR exp1, one factor at a time, each a table with 95% CIs over seeds.

    python recipes/ablations.py             # 5 seeds, about 15 minutes on 2 cores
    python recipes/ablations.py --quick     # a smoke version (CI)
    python recipes/ablations.py --report-only

Factors (the default is marked and shared by every block, so it runs once):
- ``residual x bootstrap``: the squared residual (default) or the paper's |mean ŵδ|, a target Q (``SoftUpdate``,
  default) or the residual gradient (the paper's form);
- ``ratio divergence``: the Basu power divergence with α = ½ (the paper, default), α = 1, and the KL limit α → 0;
- ``expert noise τ``: 0.05 (the paper, default), 0.2, 0.5 (at 0.5 the expert is the behaviour's gain, 0.5K);
- ``expert data size m``: 100, 300, 1,000 (default) and 3,000 expert episodes of 20 steps;
- ``behaviour noise``: σ_b = 0.25, 0.5 (default), 1.0, with unweighted BRM beside WBRM (BRM reads no expert data, so
  τ and m cannot move it: its default row stands for both).

Every run uses the budget of ``recipes/paper_tables.py`` (``table`` in ``configs/study_budgets.yaml``; ``--quick``:
``table_quick``): 2×128 networks, 2,000 Q steps. The
metrics: paired regret against the exact optimum, Q̂ error relative to Q*'s spread and Q̂'s bias on expert samples,
ŵ's relative L2 error against the exact ratio, the ESS of the weights over D (of about 18,000), and the held-out
Bellman residual. Outputs in ``--out``: one directory per cell and seed and ``tables.md``.
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

from studies.runs import study_budget

COMMON = ["env=lqr_exp1", *study_budget("quiet")]
DEFAULT = "default"
BLOCKS = {
    "residual x bootstrap": {
        "squared, target (default)": [],
        "squared, residual gradient": ["q.bootstrap=residual_gradient"],
        "absolute_mean, target": ["q.residual=absolute_mean"],
        "absolute_mean, residual gradient (paper)": ["q.residual=absolute_mean", "q.bootstrap=residual_gradient"],
    },
    "ratio divergence": {
        "Basu α=½ (paper, default)": [],
        "Basu α=1": ["ratio.alpha=1.0"],
        "KL (α → 0)": ["ratio.divergence=kl"],
    },
    "expert noise τ": {
        "τ=0.05 (paper, default)": [],
        "τ=0.2": ["env.lqr_data.expert_tau=0.2"],
        "τ=0.5": ["env.lqr_data.expert_tau=0.5"],
    },
    "expert data size m": {
        "m=100 episodes": ["env.lqr_data.expert_episodes=100"],
        "m=300 episodes": ["env.lqr_data.expert_episodes=300"],
        "m=1000 episodes (default)": [],
        "m=3000 episodes": ["env.lqr_data.expert_episodes=3000"],
    },
    "behaviour noise": {
        "σ_b=0.25": ["env.lqr_data.behaviour_noise_std=0.25"],
        "σ_b=0.5 (default)": [],
        "σ_b=1.0": ["env.lqr_data.behaviour_noise_std=1.0"],
    },
}
#: the blocks where unweighted BRM runs beside WBRM (elsewhere BRM is unaffected by the factor or not applicable)
WITH_BRM = ("behaviour noise",)
METRICS = {
    "paired regret": "final.regret",
    "Q̂ error / spread (expert)": "final.q_error_expert",
    "Q̂ bias (expert)": "final.q_bias_expert",
    "ŵ rel. L2 error": "ratio.ratio_relative_l2",
    "ESS of weights": "weights.ess",
    "held-out Bellman residual": "final.held_out_bellman_residual",
}


def _slug(override: str) -> str:
    """``env.lqr_data.expert_tau=0.2`` -> ``expert_tau=0.2``."""
    key, value = override.split("=", 1)
    return f"{key.split('.')[-1]}={value}"


def build_cells(quick: bool) -> list[dict]:
    """One cell per distinct run configuration; a setting shared by several blocks (the default) runs once and is
    listed under each of them in the tables."""
    cells: dict[tuple, dict] = {}
    for block, settings in BLOCKS.items():
        algos = ("wbrm", "brm") if block in WITH_BRM else ("wbrm",)
        for setting, overrides in settings.items():
            for algo in algos:
                key = (algo, tuple(overrides))
                cell = cells.setdefault(key, {
                    "block": "ablation", "env": "lqr_exp1", "method": algo,
                    "setting": DEFAULT if not overrides else "_".join(_slug(o) for o in overrides),
                    "overrides": [*COMMON, f"algo={algo}", *overrides], "blocks": [],
                })
                cell["blocks"].append((block, setting))
    out = list(cells.values())
    if quick:
        out = [c for c in out if c["setting"] == DEFAULT or c["setting"] == "divergence=kl"]
    return out


def tables(out: Path, cells: list[dict]) -> str:
    from torchrl_wbrm.training.reporting import load_results, results_table

    records = load_results(out)
    parts = []
    for block in BLOCKS:
        recs = []
        for cell in cells:
            for b, setting in cell["blocks"]:
                if b != block:
                    continue
                for r in records:
                    s = r.get("study", {})
                    if s.get("setting") == cell["setting"] and s.get("method") == cell["method"]:
                        recs.append({**r, "ablation": {"setting": setting, "algo": cell["method"]}})
        if recs:
            parts.append(f"### {block} (LQR exp1)\n\n" + results_table(recs, ["=ablation.setting", "=ablation.algo"], METRICS))
    return "\n\n".join(parts)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="tiny budgets, 2 settings, 1 seed")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--out", default=None,
                        help="where the runs and tables go (default results/ablations; --quick: results/ablations_quick)")
    parser.add_argument("--report-only", action="store_true")
    from studies.docs_fragments import add_docs_dir_argument, docs_dir_from_args, publish_study

    add_docs_dir_argument(parser)
    args = parser.parse_args()
    os.environ.setdefault("MPLBACKEND", "Agg")
    out = Path(args.out or ("results/ablations_quick" if args.quick else "results/ablations"))  # a smoke run never mixes with the full one
    cells = build_cells(args.quick)
    if not args.report_only:
        from studies.runs import run_cells

        run_cells(cells, range(1 if args.quick else args.seeds), study_budget("table_quick" if args.quick else "table"),
                  out, jobs=args.jobs)
    text = tables(out, cells)
    (out / "tables.md").write_text(text + "\n")
    print(text)
    from torchrl_wbrm.training.reporting import load_results

    name = "table_quick" if args.quick else "table"
    publish_study("ablations", out / "tables.md", docs_dir_from_args(args.docs_dir, args.quick),
                  seeds={r["seed"] for r in load_results(out) if "seed" in r}, budget=name,
                  budget_overrides=study_budget(name))
    from torchrl_wbrm.training.logging import log_study_summary  # the group's wandb summary run (offline)

    log_study_summary("ablations", out, tables=[out / "tables.md"])


if __name__ == "__main__":
    main()
