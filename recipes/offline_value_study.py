"""The offline value estimate against the exact value on LQR: FQE on D (no environment) of linear policies, against
the closed-form 20-step discounted return the online evaluation measures.

    python recipes/offline_value_study.py            # exp1-3, seeds 0-4 (one process, one thread)
    python recipes/offline_value_study.py --quick    # one system, one seed, a short fit

Per system and seed: D is the recipe's default LQR data (1,000 behaviour episodes of a = −0.5 K x + N(0, 0.5²) from
x₀ ∼ N(0, I)); the policies valued are the expert's mean action −0.95 K x and the behaviour's −0.5 K x, acting
deterministically as the online evaluation runs them. The estimate is
:func:`torchrl_wbrm.ope.estimate_offline_value` in finite-horizon mode (H = 20, γ = 0.9, a 2×64 SiLU Q); the truth is
``LQREnv.policy_return`` (exact, clipped reward). Writes ``results.csv`` and ``tables.md`` to ``--out`` (default
results/offline_value) and, from a clone, the docs fragment ``offline_value``.
"""
from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import torch

SYSTEMS = ("exp1", "exp2", "exp3")
POLICIES = {"expert mean (−0.95 K x)": 0.95, "behaviour mean (−0.5 K x)": 0.5}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=2000, help="Adam steps of each FQE fit")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--out", default=None)
    from studies.docs_fragments import add_docs_dir_argument, docs_dir_from_args, publish_study

    add_docs_dir_argument(parser)
    args = parser.parse_args()
    torch.set_num_threads(1)
    from tensordict.nn import TensorDictModule

    from torchrl_wbrm.data.lqr import LQRDataConfig, make_lqr_datasets
    from torchrl_wbrm.envs import LQREnv
    from torchrl_wbrm.evaluation import mean_ci
    from torchrl_wbrm.ope import estimate_offline_value
    from torchrl_wbrm.policies.lqr import LinearGaussianPolicy

    out = Path(args.out or ("results/offline_value_quick" if args.quick else "results/offline_value"))
    out.mkdir(parents=True, exist_ok=True)
    systems = SYSTEMS[:1] if args.quick else SYSTEMS
    seeds = range(1 if args.quick else args.seeds)
    steps = 200 if args.quick else args.steps
    rows = []
    for system in systems:
        env = LQREnv(system)
        _, K = env.riccati()
        for seed in seeds:
            data_cfg = LQRDataConfig(behaviour_episodes=100 if args.quick else 2000, expert_episodes=2)
            d = make_lqr_datasets(system, data_cfg, seed=seed).transitions[:]
            for name, scale in POLICIES.items():
                t0 = time.perf_counter()
                policy = TensorDictModule(LinearGaussianPolicy(scale * K, 0.0), in_keys=["observation"],
                                          out_keys=["action"])
                est = estimate_offline_value(policy, d, gamma=env.config.gamma, horizon=env.config.horizon,
                                             steps=steps, seed=seed)
                truth = env.policy_return(scale * K, 0.0)
                rows.append({"system": system, "seed": seed, "policy": name, "estimate": est.value,
                             "ci_low": est.low, "ci_high": est.high, "truth": truth,
                             "relative_error": (est.value - truth) / abs(truth),
                             "covered": est.low <= truth <= est.high, "seconds": time.perf_counter() - t0})
                print(f"{system} seed {seed} {name}: {est.value:.3f} [{est.low:.3f}, {est.high:.3f}] vs exact "
                      f"{truth:.3f} (offline: the environment was not stepped)", flush=True)
    with open(out / "results.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    lines = ["| system | policy | exact return | offline estimate | relative error (%) | |relative error| (%) | "
             "truth inside the bootstrap CI |", "|---|---|---|---|---|---|---|"]
    for system in systems:
        for name in POLICIES:
            rs = [r for r in rows if r["system"] == system and r["policy"] == name]

            def cell(values, scale=1.0, digits=3):
                ci = mean_ci([v * scale for v in values])
                return f"{ci.mean:.{digits}f}" + (f" ± {ci.half_width:.{digits}f}" if len(values) > 1 else "")

            lines.append(f"| {system} | {name} | {rs[0]['truth']:.3f} | {cell([r['estimate'] for r in rs])} | "
                         f"{cell([r['relative_error'] for r in rs], 100)} | "
                         f"{cell([abs(r['relative_error']) for r in rs], 100)} | "
                         f"{sum(r['covered'] for r in rs)} of {len(rs)} |")
    text = "\n".join(lines)
    (out / "tables.md").write_text(text + "\n")
    print(text)
    publish_study("offline_value", out / "tables.md", docs_dir_from_args(args.docs_dir, args.quick), seeds=seeds,
                  budget=f"{steps} Adam steps per FQE fit (batch 256, lr 1e-3, τ 0.05, a 2×64 SiLU Q)")


if __name__ == "__main__":
    main()
