"""Where does the density ratio pay? Weighted against unweighted FQE and FQI on LQR, with Q classes that cannot fit
Q everywhere, scored against exact answers.

    python recipes/misspecified_study.py                 # the study: 10 seeds, both behaviours (one process, 1 thread)
    python recipes/misspecified_study.py --quick         # a smoke version (two classes, tiny data; CI runs it)
    python recipes/misspecified_study.py --seeds 10 --first-seed 10 --out <new>   # fresh seeds 10-19

Per seed and behaviour: LQR exp1; D = 1,000 behaviour episodes (a = −0.5 K x + N(0, 1)) starting from x₀ ∼ N(0, I)
("near") or N(0, 3² I) ("far"), 1,000 more for S^b, and S^e = 250 expert episodes (a = 0.95 (−K x) + 0.05 N(0, I)).
Weightings of the residual: none, the project's learned ratio ŵ (stage 1, ``fit_density_ratio`` at its defaults) and
the exact ratio w of the two policies' occupancies. Q classes: linear in the polynomial features of (x, a) of degree 1
and 2 (least-squares FQE/FQI, :mod:`torchrl_wbrm.ope.linear_fqe`), and SiLU MLPs 2×8, 2×64 and 2×256 (FQE by
``FQELoss`` with Adam). Scores, each against an exact answer:

- Q̂'s error on the expert's state-action distribution: RMS(Q̂ − Q^π)/std(Q^π) on 2,000 fresh expert samples, Q^π
  the closed form of the expert's mean policy π(x) = −0.95 K x (unclipped reward, :mod:`~torchrl_wbrm.evaluation.
  lqr_policy_value`);
- the error of the expert's value estimate: mean Q̂(x₀, π(x₀)) over 2,000 fresh x₀ ∼ N(0, I) minus the exact
  E[V^π(x₀)];
- the greedy policy's paired regret (linear classes: FQI's greedy policy in closed form; 1,000 episodes, exact
  finite-horizon optimum).

Writes ``results.csv``, ``tables.md`` and ``misspecified_q.png`` to ``--out`` (default results/misspecified_q) and,
from a clone, the docs fragment and figure (``--docs-dir``).
"""
from __future__ import annotations

import argparse
import csv
import os
import time
from pathlib import Path

import torch

CLASSES = ("poly1", "poly2", "mlp8", "mlp64", "mlp256")
WEIGHTINGS = ("uniform", "learned ŵ", "exact w")
BEHAVIOURS = {"near (x₀ ∼ N(0, I))": None, "far (x₀ ∼ N(0, 3² I))": 3.0}
METRICS = ("q_error", "value_error", "regret")


def run_seed(seed: int, start_std, *, quick: bool, mlp_steps: int, classes=CLASSES) -> list[dict]:
    """Every class × weighting for one seed and behaviour: a list of result rows."""
    from tensordict import TensorDict
    from tensordict.nn import TensorDictModule

    from torchrl_wbrm.data.lqr import LQRDataConfig, make_lqr_datasets
    from torchrl_wbrm.envs import LQREnv
    from torchrl_wbrm.evaluation import lqr_paired_regret, q_error
    from torchrl_wbrm.objectives.functional import effective_sample_size
    from torchrl_wbrm.ope.linear_fqe import GreedyQuadraticPolicy, LinearQ, least_squares_fqe
    from torchrl_wbrm.evaluation.lqr_policy_value import linear_policy_q, linear_policy_value
    from torchrl_wbrm.ope.offline_value import fit_fqe, value_at
    from torchrl_wbrm.modules import PolynomialFeatures
    from torchrl_wbrm.objectives import FQELoss
    from torchrl_wbrm.policies import make_lqr_behaviour, make_lqr_expert
    from torchrl_wbrm.policies.lqr import LinearGaussianPolicy, lqr_true_density_ratio
    from torchrl_wbrm.ratio import compute_density_ratio, fit_density_ratio

    env = LQREnv("exp1")
    _, K = env.riccati()
    tau = 0.05
    gain = (1 - tau) * K
    episodes = 60 if quick else 1000
    data_cfg = LQRDataConfig(behaviour_episodes=2 * episodes, expert_episodes=30 if quick else 250, expert_tau=tau,
                             behaviour_gain_scale=0.5, behaviour_noise_std=1.0, behaviour_initial_std=start_std)
    ds = make_lqr_datasets("exp1", data_cfg, seed=seed)
    d = ds.transitions[:]
    scoring = make_lqr_datasets("exp1", LQRDataConfig(behaviour_episodes=4, expert_episodes=100, expert_tau=tau),
                                seed=10_000 + seed).expert_samples[:]
    expert_x, expert_a = scoring["observation"], scoring["action"]
    q_true = linear_policy_q(env, gain, 0.0, expert_x.double(), expert_a.double())
    P, v0 = linear_policy_value(env, gain, 0.0)
    true_value = v0 - float(torch.trace(torch.as_tensor(P)))
    starts = TensorDict({"observation": torch.randn(2000, 2, generator=torch.Generator().manual_seed(20_000 + seed))},
                        [2000])
    policy = TensorDictModule(LinearGaussianPolicy(gain, 0.0), in_keys=["observation"], out_keys=["action"])

    fit = fit_density_ratio(ds.behaviour_samples, ds.expert_samples, seed=seed, steps=300 if quick else 1500)
    true_ratio = lqr_true_density_ratio(env, make_lqr_expert(env, tau=tau),
                                        make_lqr_behaviour(env, gain_scale=0.5, noise_std=1.0),
                                        behaviour_initial_std=start_std)
    weights = {"uniform": None,
               "learned ŵ": compute_density_ratio(fit.network, d).reshape(-1).detach(),
               "exact w": true_ratio(d.select("observation", "action"))["density_ratio"].reshape(-1).detach()}
    iterations = 40 if quick else 300
    rows = []
    for cls in classes:
        for name, w in weights.items():
            t0 = time.perf_counter()
            row = {"seed": seed, "class": cls, "weighting": name,
                   "ess_fraction": 1.0 if w is None else effective_sample_size(w).item() / w.numel()}
            if cls.startswith("poly"):
                degree = int(cls[-1])
                features = PolynomialFeatures(degree)
                initial = float(d["next", "reward"].mean()) / (1 - env.config.gamma)
                q_module = TensorDictModule(LinearQ(2, 2, degree=degree, initial_value=initial),
                                            in_keys=["observation", "action"], out_keys=["state_action_value"])
                loss = FQELoss(q_module, policy)
                loss.make_value_estimator(gamma=env.config.gamma)
                least_squares_fqe(loss, d, features, weight=w, iterations=iterations)
                # FQI: the same iteration with π the greedy policy of the target Q
                greedy = GreedyQuadraticPolicy(LinearQ(2, 2, degree=degree, initial_value=initial), 2,
                                               env.config.action_bound)
                greedy_module = TensorDictModule(greedy, in_keys=["observation"], out_keys=["action"])
                fqi = FQELoss(TensorDictModule(LinearQ(2, 2, degree=degree, initial_value=initial),
                                               in_keys=["observation", "action"], out_keys=["state_action_value"]),
                              greedy_module)
                fqi.make_value_estimator(gamma=env.config.gamma)
                fit_info = least_squares_fqe(fqi, d, features, weight=w, greedy=greedy, iterations=iterations)
                greedy.set_theta(fqi.value_network_params.get(("module", "theta")))
                regret = lqr_paired_regret("exp1", greedy_module, episodes=200 if quick else 1000, seed=seed)
                row["regret"] = regret["regret"].mean
                row["fqi_converged"] = fit_info["converged"]
            else:
                width = int(cls[3:])
                data = d if w is None else d.clone().set("density_ratio", w.unsqueeze(-1).to(torch.float32))
                loss, _ = fit_fqe(policy, data, gamma=env.config.gamma, horizon=None,
                                  weight_key=None if w is None else "density_ratio", num_cells=(width, width),
                                  steps=mlp_steps, seed=seed)
                row["regret"] = float("nan")
            q_hat = loss.q_value(TensorDict({"observation": expert_x, "action": expert_a}, [expert_x.shape[0]]))
            row["q_error"] = q_error(q_hat, q_true)["relative_spread_error"]
            row["value_error"] = value_at(loss, starts).double().mean().item() - true_value
            row["seconds"] = time.perf_counter() - t0
            rows.append(row)
    return rows


def summarise(rows: list[dict]) -> str:
    """Markdown tables: mean ± 95% CI over seeds per behaviour, class and weighting, then the paired differences."""
    from torchrl_wbrm.evaluation import mean_ci

    def cell(values, digits=3):
        values = [v for v in values if v == v]
        if not values:
            return "—"
        ci = mean_ci(values)
        return f"{ci.mean:.{digits}f} ± {ci.half_width:.{digits}f}" if len(values) > 1 else f"{ci.mean:.{digits}f}"

    lines = []
    for behaviour in BEHAVIOURS:
        sub = [r for r in rows if r["behaviour"] == behaviour]
        if not sub:
            continue
        seeds = sorted({r["seed"] for r in sub})
        lines += [f"### Behaviour {behaviour}, {len(seeds)} seeds", "",
                  "| Q class | weighting | Q̂ error on expert (× std Q^π) | value error (V̂ − V) | |value error| | "
                  "greedy regret (FQI) | ESS / n |", "|---|---|---|---|---|---|---|"]
        for cls in CLASSES:
            for name in WEIGHTINGS:
                rs = [r for r in sub if r["class"] == cls and r["weighting"] == name]
                if not rs:
                    continue
                lines.append(f"| {cls} | {name} | {cell([r['q_error'] for r in rs])} | "
                             f"{cell([r['value_error'] for r in rs])} | {cell([abs(r['value_error']) for r in rs])} | "
                             f"{cell([r['regret'] for r in rs], 4)} | {cell([r['ess_fraction'] for r in rs])} |")
        lines += ["", f"Paired differences, weighted − uniform (same seed; below 0: the weighting helps), {behaviour}:",
                  "", "| Q class | weighting | Δ Q̂ error | Δ |value error| | Δ regret |", "|---|---|---|---|---|"]
        for cls in CLASSES:
            base = {r["seed"]: r for r in sub if r["class"] == cls and r["weighting"] == "uniform"}
            for name in WEIGHTINGS[1:]:
                rs = [r for r in sub if r["class"] == cls and r["weighting"] == name and r["seed"] in base]
                if not rs:
                    continue
                dq = [r["q_error"] - base[r["seed"]]["q_error"] for r in rs]
                dv = [abs(r["value_error"]) - abs(base[r["seed"]]["value_error"]) for r in rs]
                dr = [r["regret"] - base[r["seed"]]["regret"] for r in rs]
                lines.append(f"| {cls} | {name} | {cell(dq)} | {cell(dv)} | {cell(dr, 4)} |")
        lines.append("")
    return "\n".join(lines)


def plot(rows: list[dict], path: Path) -> Path:
    """Q̂'s error on the expert's distribution per class, one panel per behaviour, mean and 95% CI over seeds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchrl_wbrm.evaluation import mean_ci

    fig, axes = plt.subplots(1, len(BEHAVIOURS), figsize=(11, 4), sharey=True)
    for ax, behaviour in zip(axes, BEHAVIOURS):
        for k, name in enumerate(WEIGHTINGS):
            means, errs, xs = [], [], []
            for i, cls in enumerate(CLASSES):
                vals = [r["q_error"] for r in rows if r["behaviour"] == behaviour and r["class"] == cls
                        and r["weighting"] == name]
                if not vals:
                    continue
                ci = mean_ci(vals)
                xs.append(i + (k - 1) * 0.25)
                means.append(ci.mean)
                errs.append(0.0 if len(vals) < 2 else ci.half_width)
            ax.errorbar(xs, means, yerr=errs, fmt="o", capsize=3, label=name)
        ax.set_xticks(range(len(CLASSES)), CLASSES)
        ax.set_yscale("log")
        ax.set_title(f"behaviour {behaviour}")
        ax.set_xlabel("Q class")
    axes[0].set_ylabel("RMS(Q̂ − Q^π) / std(Q^π) on expert samples")
    axes[0].legend()
    fig.suptitle("FQE of the expert on LQR exp1: weighted vs unweighted (mean, 95% CI over seeds)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--mlp-steps", type=int, default=1000, help="Adam steps of each MLP's FQE fit")
    parser.add_argument("--quick", action="store_true", help="a smoke version: 1 seed, small data and budgets")
    parser.add_argument("--out", default=None, help="output folder (default results/misspecified_q[_quick])")
    from studies.docs_fragments import add_docs_dir_argument, docs_dir_from_args, publish_study

    add_docs_dir_argument(parser)
    args = parser.parse_args()
    torch.set_num_threads(1)
    os.environ.setdefault("MPLBACKEND", "Agg")
    out = Path(args.out or ("results/misspecified_q_quick" if args.quick else "results/misspecified_q"))
    out.mkdir(parents=True, exist_ok=True)
    seeds = range(args.first_seed, args.first_seed + (1 if args.quick else args.seeds))
    mlp_steps = 100 if args.quick else args.mlp_steps
    rows = []
    for behaviour, start in BEHAVIOURS.items():
        for seed in seeds:
            t0 = time.perf_counter()
            classes = ("poly2", "mlp8") if args.quick else CLASSES
            for row in run_seed(seed, start, quick=args.quick, mlp_steps=mlp_steps, classes=classes):
                rows.append({"behaviour": behaviour, **row})
            print(f"{behaviour} seed {seed}: {time.perf_counter() - t0:.0f}s", flush=True)
    with open(out / "results.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    text = summarise(rows)
    (out / "tables.md").write_text(text + "\n")
    figure = plot(rows, out / "misspecified_q.png")
    print(text)
    publish_study("misspecified_q", out / "tables.md", docs_dir_from_args(args.docs_dir, args.quick),
                  seeds=seeds, budget=f"{mlp_steps} Adam steps per MLP fit (batch 256, lr 1e-3, τ 0.05); "
                  "least squares to convergence (≤ 300 iterations) for the linear classes", figures=[figure])


if __name__ == "__main__":
    main()
