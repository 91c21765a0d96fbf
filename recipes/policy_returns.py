"""Measure the data-generating policies' returns and print the README's table of them.

    python recipes/policy_returns.py [--episodes 10000] [--mc-episodes 100] [--seed 0]

LQR: 20-step discounted returns (gamma = 0.9) of the exact optimum (analytic), the expert and the behaviour
(simulated, mean +/- 95% CI, and the exact unclipped figure). MountainCarContinuous-v0: undiscounted returns
over ``--mc-episodes`` episodes of the noisy expert heuristic, the noise-free heuristic at power 0.3, and
uniform random actions.
"""
from __future__ import annotations

import argparse
import math

import torch

from torchrl_wbrm.data import collect_transitions, episode_returns
from torchrl_wbrm.envs import REWARD_CAP_87_84, make_lqr_env
from torchrl_wbrm.policies import (
    make_lqr_behaviour,
    make_lqr_expert,
    make_mountain_car_env,
    make_mountain_car_expert,
    make_mountain_car_random_policy,
)


def mean_ci(x: torch.Tensor) -> str:
    return f"{x.mean().item():.3f} ± {1.96 * x.std().item() / math.sqrt(len(x)):.3f}"


def dqn_grid_regret(bins: list[int], *, episodes: int, seed: int) -> None:
    """What DQN's action grid alone costs: the paired regret (LQR exp1) of the exact optimal policy with its action
    snapped to the nearest point of the grid that ``algo=dqn`` uses (``ActionGrid``, torchrl's ``ActionDiscretizer``)."""
    from tensordict.nn import TensorDictModule, TensorDictSequential

    from torchrl_wbrm.evaluation import lqr_paired_regret
    from torchrl_wbrm.policies import make_lqr_optimal_policy
    from torchrl_wbrm.modules import ActionGrid

    if not bins:
        return
    env = make_lqr_env("exp1")
    print("| LQR exp1: the exact optimum snapped to DQN's grid, values per coordinate | paired regret ± 95% CI |")
    print("|---|---|")
    for n in bins:
        grid = ActionGrid.from_lqr_env("exp1", n)
        snap = TensorDictModule(lambda a, grid=grid: grid(grid.index(a)), in_keys=["action"], out_keys=["action"])
        res = lqr_paired_regret("exp1", TensorDictSequential(make_lqr_optimal_policy(env.base_env), snap),
                                episodes=episodes, seed=seed)
        print(f"| {n} ({n ** 2} joint actions) | {res['regret'].mean:.4f} ± {res['regret'].half_width:.4f} |")
    print()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=10_000)
    parser.add_argument("--mc-episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--skip-mountain-car", action="store_true")
    parser.add_argument("--dqn-bins", type=int, nargs="*", default=[11, 21, 41],
                        help="grids (values per action coordinate) for the snapped-optimum regret")
    args = parser.parse_args()

    print("| LQR | exact optimum (clipped reward) | exact optimum (unclipped) | expert τ=0.05 (measured) | expert (exact, unclipped) | behaviour (measured) | behaviour (exact, unclipped) |")
    print("|---|---|---|---|---|---|---|")
    for exp in ("exp1", "exp2", "exp3"):
        env = make_lqr_env(exp, batch_size=[min(args.episodes, 10_000)], seed=args.seed)
        base = env.base_env
        row = [exp, f"{base.optimal_return():.4f}", f"{base.optimal_return(clipped=False):.4f}"]
        for k, pol in enumerate((make_lqr_expert(env), make_lqr_behaviour(env))):
            data = collect_transitions(env, pol, args.episodes * base.config.horizon, seed=args.seed + 10 * k)
            exact = base.policy_return(pol.module.gain, pol.module.noise_std, clipped=False)
            row += [mean_ci(episode_returns(data, gamma=base.config.gamma)), f"{exact:.4f}"]
        print("| " + " | ".join(row) + " |")
    print(f"\nThe paper's '87.84' = 10·Σ_(t<20) 0.9^t = {REWARD_CAP_87_84:.4f} (the reward cap).\n")
    dqn_grid_regret(args.dqn_bins, episodes=1000, seed=args.seed)

    if args.skip_mountain_car:
        return
    print(f"| MountainCarContinuous-v0 ({args.mc_episodes} episodes) | mean return ± 95% CI | mean length |")
    print("|---|---|---|")
    env = make_mountain_car_env(seed=args.seed)
    policies = {
        "expert: 0.9·sign(v) + 0.1·U(−1,1)": make_mountain_car_expert(),
        "heuristic 0.3·sign(v), no noise": make_mountain_car_expert(power=0.3, tau=0.0),
        "uniform random actions": make_mountain_car_random_policy(env.action_spec),
    }
    for name, pol in policies.items():
        returns, lengths, seed = [], [], args.seed
        while len(returns) < args.mc_episodes:
            data = collect_transitions(env, pol, 1000 * 20, seed=seed)
            returns += episode_returns(data).tolist()
            ids, counts = torch.unique(data["episode"], return_counts=True)
            lengths += counts[: len(episode_returns(data))].tolist()
            seed += 1
        r = torch.tensor(returns[: args.mc_episodes])
        print(f"| {name} | {mean_ci(r)} | {sum(lengths[: args.mc_episodes]) / args.mc_episodes:.0f} |")


if __name__ == "__main__":
    main()
