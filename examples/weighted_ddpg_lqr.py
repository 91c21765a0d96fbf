"""Weighting another TorchRL loss: TorchRL's ``DDPGLoss`` with ŵ as its per-sample ``"priority_weight"``.

    python examples/weighted_ddpg_lqr.py            # the full budget
    python examples/weighted_ddpg_lqr.py --quick    # a few seconds (CI)

Any TorchRL loss that reads ``"priority_weight"`` (``DDPGLoss``, ``TD3Loss``, ``TD3BCLoss``, ``SACLoss``,
``DQNLoss``, ...) becomes ŵ-weighted once stage 1 has stored ŵ under that key: here both DDPG's critic loss and
its actor loss ``−Q(x, μ(x))`` are averaged with ŵ as the sample weights (TorchRL reduces them as
``Σ ŵᵢ lᵢ / Σ ŵᵢ``).
The script trains DDPG with and without the weights on the same data and scores both by their exact paired regret
(``--quick`` trains the weighted one only).
"""
from __future__ import annotations

import argparse
import tempfile

import torch
from torchrl.data import Bounded
from torchrl.objectives import DDPGLoss, SoftUpdate
from torchrl.record.loggers.csv import CSVLogger

from torchrl_wbrm.data import LQRDataConfig, make_lqr_datasets
from torchrl_wbrm.envs import LQREnv
from torchrl_wbrm.evaluation import lqr_paired_regret
from torchrl_wbrm.modules import make_deterministic_actor, make_q_network
from torchrl_wbrm.ratio import fit_density_ratio, store_density_ratio

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--quick", action="store_true", help="a few-second budget (CI)")
parser.add_argument("--seed", type=int, default=0)
parser.add_argument("--log-dir", default=None, help="CSV logs (defaults to a temporary folder)")
args = parser.parse_args()
torch.set_num_threads(1)
torch.manual_seed(args.seed)
steps, ratio_steps, episodes, cells = (500, 300, 600, (64, 64)) if args.quick else (3000, 1500, 2000, (256, 256))

# ---- data (LQR exp1) and stage 1: ŵ stored over D as "priority_weight" (ŵ^0.25, mean 1)
datasets = make_lqr_datasets("exp1", LQRDataConfig(behaviour_episodes=episodes, expert_episodes=episodes // 2),
                             seed=args.seed)
env = LQREnv("exp1")
gamma, bound = env.config.gamma, env.config.action_bound
action_spec = Bounded(-bound, bound, (env.config.action_dim,))
fit = fit_density_ratio(datasets.behaviour_samples, datasets.expert_samples, steps=ratio_steps, batch_size=256,
                        num_cells=(64, 64), lr=3e-3, seed=args.seed)
store_density_ratio(datasets.transitions, ratio_network=fit.network, key="priority_weight", temper=0.25)
mean_reward = datasets.transitions[:]["next", "reward"].mean().item()
log_dir = args.log_dir or tempfile.mkdtemp(prefix="weighted_ddpg_")


def train(weighted: bool) -> dict:
    """TorchRL's offline DDPG loop; returns the exact paired regret of the actor."""
    torch.manual_seed(args.seed)
    actor = make_deterministic_actor(env.config.state_dim, action_spec, num_cells=cells)
    q = make_q_network(env.config.state_dim, env.config.action_dim, num_cells=cells, activation="SiLU",
                       initial_bias=mean_reward / (1 - gamma))
    loss = DDPGLoss(actor, q, delay_actor=True, delay_value=True, loss_function="l2",
                    use_prioritized_weights="auto" if weighted else False)
    loss.make_value_estimator(gamma=gamma)
    updater = SoftUpdate(loss, tau=0.05)
    critic_optim = torch.optim.Adam(loss.value_network_params.values(True, True), lr=1e-3)
    actor_optim = torch.optim.Adam(loss.actor_network_params.values(True, True), lr=1e-3)
    logger = CSVLogger(exp_name="weighted_ddpg" if weighted else "ddpg", log_dir=log_dir)
    torch.manual_seed(args.seed + 1)  # the same batches with and without weights
    for step in range(1, steps + 1):
        batch = datasets.transitions.sample(256)  # carries "priority_weight" = ŵ
        out = loss(batch)
        critic_optim.zero_grad()
        actor_optim.zero_grad()
        (out["loss_value"] + out["loss_actor"]).backward()
        critic_optim.step()
        actor_optim.step()
        updater.step()
        if step % 100 == 0:
            logger.log_scalar("loss_value", out["loss_value"].item(), step=step)
    return lqr_paired_regret("exp1", actor, episodes=1000, seed=1_000_000 + args.seed)["regret"]


variants = (("ŵ-weighted DDPG", True),) if args.quick else (("DDPG", False), ("ŵ-weighted DDPG", True))
for name, weighted in variants:
    regret = train(weighted)
    print(f"{name:<16} paired regret {regret.mean:.4f} ± {regret.half_width:.4f}")
behaviour = env.optimal_return() - env.policy_return(0.5 * env.riccati()[1])
print(f"{'behaviour mean':<16} exact regret  {behaviour:.4f}   (a = −0.5Kx, the behaviour policy without its noise)")
