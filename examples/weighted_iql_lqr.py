"""Weighting a loss that ignores ``"priority_weight"``: TorchRL's ``IQLLoss`` with ŵ through ``WeightedLoss``.

    python examples/weighted_iql_lqr.py            # the full budget
    python examples/weighted_iql_lqr.py --quick    # CI

``IQLLoss`` does not read ``"priority_weight"`` (only the losses of ``NATIVE_PRIORITY_WEIGHT_LOSSES`` do), so ŵ stored
there would leave it unweighted. Built with ``reduction="none"`` it gives its three terms per sample;
``WeightedLoss(iql, weight_key="density_ratio")`` reduces each as ``Σ ŵᵢ lᵢ / Σ ŵᵢ``, with IQL's own keys, value
estimator and target parameters (``SoftUpdate`` is built on the wrapper). The script trains the weighted IQL and its
unweighted twin (the same networks, seeds and batches, ``IQLLoss`` with its default reduction) on LQR exp1 and scores
both by their exact paired regret against the optimal policy (``--quick`` trains the weighted one only).
"""
from __future__ import annotations

import argparse
import tempfile

import torch
from torchrl.data import Bounded
from torchrl.objectives import IQLLoss, SoftUpdate
from torchrl.record.loggers.csv import CSVLogger

from torchrl_wbrm.data import LQRDataConfig, make_lqr_datasets
from torchrl_wbrm.envs import LQREnv
from torchrl_wbrm.evaluation import lqr_paired_regret
from torchrl_wbrm.modules import initial_q_value, make_q_network, make_tanh_normal_actor
from torchrl_wbrm.objectives import WeightedLoss
from torchrl_wbrm.ratio import fit_density_ratio, store_density_ratio

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--quick", action="store_true", help="a CI budget (about half a minute)")
parser.add_argument("--seed", type=int, default=0)
parser.add_argument("--log-dir", default=None, help="CSV logs (defaults to a temporary folder)")
args = parser.parse_args()
torch.set_num_threads(1)
torch.manual_seed(args.seed)
steps, ratio_steps, episodes, cells = (600, 300, 600, (64, 64)) if args.quick else (3000, 1500, 2000, (256, 256))

# ---- data (LQR exp1) and stage 1: ŵ stored over D as "density_ratio" (ŵ^0.25, mean 1)
datasets = make_lqr_datasets("exp1", LQRDataConfig(behaviour_episodes=episodes, expert_episodes=episodes // 2),
                             seed=args.seed)
env = LQREnv("exp1")
gamma, bound = env.config.gamma, env.config.action_bound
obs_dim, act_dim = env.config.state_dim, env.config.action_dim
action_spec = Bounded(-bound, bound, (act_dim,))
replay_buffer = datasets.transitions
fit = fit_density_ratio(datasets.behaviour_samples, datasets.expert_samples, steps=ratio_steps, batch_size=256,
                        num_cells=(64, 64), lr=3e-3, seed=args.seed)
store_density_ratio(replay_buffer, ratio_network=fit.network, key="density_ratio", temper=0.25)
q_start = initial_q_value(replay_buffer, gamma)  # mean(r) / (1 − γ): where Q and V start
log_dir = args.log_dir or tempfile.mkdtemp(prefix="weighted_iql_")


def train(weighted: bool) -> dict:
    """TorchRL's offline IQL loop; returns the paired regret of the actor's deterministic action."""
    torch.manual_seed(args.seed)
    actor = make_tanh_normal_actor(obs_dim, action_spec, num_cells=cells)
    qvalue = make_q_network(obs_dim, act_dim, num_cells=cells, activation="SiLU", initial_bias=q_start)
    value = make_q_network(obs_dim, 0, num_cells=cells, activation="SiLU", initial_bias=q_start,
                           in_keys=("observation",), out_key="state_value")
    settings = dict(loss_function="l2", expectile=0.7, temperature=3.0)
    if weighted:
        loss = WeightedLoss(IQLLoss(actor, qvalue, value, reduction="none", scalar_output_mode="exclude", **settings),
                            weight_key="density_ratio")
    else:
        loss = IQLLoss(actor, qvalue, value, **settings)
    loss.make_value_estimator(gamma=gamma)
    updater = SoftUpdate(loss, tau=0.05)
    optimiser = torch.optim.Adam(loss.parameters(), lr=1e-3)
    logger = CSVLogger(exp_name="weighted_iql" if weighted else "iql", log_dir=log_dir)
    torch.manual_seed(args.seed + 1)  # the same batches with and without weights
    for step in range(1, steps + 1):
        batch = replay_buffer.sample(256)  # carries "density_ratio" = ŵ
        out = loss(batch)
        optimiser.zero_grad()
        (out["loss_actor"] + out["loss_qvalue"] + out["loss_value"]).backward()  # each reaches its own network
        optimiser.step()
        updater.step()
        if step % 100 == 0:
            logger.log_scalar("loss_qvalue", out["loss_qvalue"].item(), step=step)
    return lqr_paired_regret("exp1", actor, episodes=1000, seed=1_000_000 + args.seed)


print(f"stage 1: best held-out loss {fit.best_loss:.4f} at step {fit.best_step} of {fit.steps_run}")
variants = (("ŵ-weighted IQL", True),) if args.quick else (("IQL", False), ("ŵ-weighted IQL", True))
for name, weighted in variants:
    result = train(weighted)
    print(f"{name:<15} paired regret {result['regret'].mean:.4f} ± {result['regret'].half_width:.4f}   "
          f"return {result['return'].mean:.3f} (exact optimum {result['optimal_return_exact']:.4f})")
behaviour = env.optimal_return() - env.policy_return(0.5 * env.riccati()[1])
print(f"{'behaviour mean':<15} exact regret  {behaviour:.4f}   (a = −0.5Kx, the behaviour policy without its noise)")
