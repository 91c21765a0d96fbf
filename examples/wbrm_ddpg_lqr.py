"""WBRM in a TorchRL-style offline DDPG loop: ``WeightedBellmanLoss`` replaces ``DDPGLoss``.

    python examples/wbrm_ddpg_lqr.py            # the full budget
    python examples/wbrm_ddpg_lqr.py --quick    # a few seconds (CI)

The loop is TorchRL's offline actor-critic loop (replay buffer, one critic and one actor optimiser, ``SoftUpdate``,
a logger). The critic's loss is the paper's ŵ-weighted Bellman residual ``mean ŵ δ²``; the actor maximises
``Q(x, μ(x))`` as in DDPG (``"loss_actor"`` of the same module). Stage 1 (fit ŵ, store it over D under
``"density_ratio"``) comes from ``torchrl_wbrm.ratio``. The result is scored by its exact paired regret against the
optimal LQR policy.
"""
from __future__ import annotations

import argparse
import tempfile

import torch
from torchrl.data import Bounded
from torchrl.objectives import SoftUpdate
from torchrl.record.loggers.csv import CSVLogger

from torchrl_wbrm.data import LQRDataConfig, make_lqr_datasets
from torchrl_wbrm.envs import LQREnv
from torchrl_wbrm.evaluation import lqr_paired_regret
from torchrl_wbrm.modules import initial_q_value, make_deterministic_actor, make_q_network
from torchrl_wbrm.objectives import WeightedBellmanLoss
from torchrl_wbrm.ratio import fit_density_ratio, store_density_ratio

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--quick", action="store_true", help="a few-second budget (CI)")
parser.add_argument("--seed", type=int, default=0)
parser.add_argument("--weight-reduction", default="mean", choices=["mean", "normalised"],
                    help="how ŵ enters the critic's mean (WeightedBellmanLoss's weight_reduction)")
parser.add_argument("--log-dir", default=None, help="CSV logs (defaults to a temporary folder)")
args = parser.parse_args()
torch.set_num_threads(1)
torch.manual_seed(args.seed)
steps, ratio_steps, episodes, cells = (500, 300, 600, (64, 64)) if args.quick else (3000, 1500, 2000, (256, 256))

# ---- data (LQR exp1): behaviour transitions D, behaviour state-actions S^b, expert state-actions S^e
datasets = make_lqr_datasets("exp1", LQRDataConfig(behaviour_episodes=episodes, expert_episodes=episodes // 2),
                             seed=args.seed)
env = LQREnv("exp1")
gamma, bound = env.config.gamma, env.config.action_bound
action_spec = Bounded(-bound, bound, (env.config.action_dim,))
replay_buffer = datasets.transitions  # a TensorDictReplayBuffer

# ---- stage 1: ŵ ≈ dP^e/dP^b (held-out early stopping), stored over D as "density_ratio" (ŵ^0.25, mean 1)
fit = fit_density_ratio(datasets.behaviour_samples, datasets.expert_samples, steps=ratio_steps, batch_size=256,
                        num_cells=(64, 64), lr=3e-3, seed=args.seed)
store_density_ratio(replay_buffer, ratio_network=fit.network, key="density_ratio", temper=0.25)
print(f"stage 1: best held-out loss {fit.best_loss:.4f} at step {fit.best_step} of {fit.steps_run}")

# ---- stage 2: the DDPG loop with WeightedBellmanLoss as the loss module
q = make_q_network(env.config.state_dim, env.config.action_dim, num_cells=cells, activation="SiLU",
                   initial_bias=initial_q_value(replay_buffer, gamma))  # mean(r) / (1 − γ): where the targets are
actor = make_deterministic_actor(env.config.state_dim, action_spec, num_cells=cells)
loss = WeightedBellmanLoss(q, actor_network=actor, residual="squared", delay_value=True,
                           weight_reduction=args.weight_reduction)
loss.make_value_estimator(gamma=gamma)
updater = SoftUpdate(loss, tau=0.05)
critic_optim = torch.optim.Adam(loss.value_network_params.values(True, True), lr=1e-3)
actor_optim = torch.optim.Adam(loss.actor_network_params.values(True, True), lr=1e-3)
logger = CSVLogger(exp_name="wbrm_ddpg_lqr", log_dir=args.log_dir or tempfile.mkdtemp(prefix="wbrm_ddpg_"))

for step in range(1, steps + 1):
    batch = replay_buffer.sample(256)  # holds "density_ratio" next to the transition keys
    out = loss(batch)  # loss_value (ŵ-weighted residual), loss_actor, td_error_mean, q_mean, weight_ess, ...
    critic_optim.zero_grad()
    actor_optim.zero_grad()
    (out["loss_value"] + out["loss_actor"]).backward()  # each loss reaches only its own network
    critic_optim.step()
    actor_optim.step()
    updater.step()
    if step % 100 == 0:
        logger.log_scalar("loss_value", out["loss_value"].item(), step=step)
        logger.log_scalar("q_mean", out["q_mean"].item(), step=step)

result = lqr_paired_regret("exp1", actor, episodes=1000, seed=1_000_000 + args.seed)
behaviour = env.optimal_return() - env.policy_return(0.5 * env.riccati()[1])
print(f"WBRM (DDPG loop)  paired regret {result['regret'].mean:.4f} ± {result['regret'].half_width:.4f}   "
      f"return {result['return'].mean:.3f} (exact optimum {result['optimal_return_exact']:.4f})")
print(f"behaviour mean    exact regret  {behaviour:.4f}   (a = −0.5Kx, the behaviour policy without its noise)")
