"""The recipe's method as a TorchRL agent built from the public pieces, on a Minari pair (Pendulum-v1).

    python examples/wbrm_minari_agent.py            # the full budget (9,000 updates, 256-unit networks)
    python examples/wbrm_minari_agent.py --quick    # a few seconds (CI)
    python examples/wbrm_minari_agent.py --data-path DIR --expert ID --behaviour ID   # your own Minari pair

Each setting that makes the method work on such data is a named line below (the tutorial
``docs/tutorials/torchrl_agent.md`` explains them):

1. ŵ's shaping: ŵ^0.25, self-normalised over D (``store_density_ratio(..., temper=0.25)``);
2. the actor's support term: TD3+BC's cloning toward the expert's actions in S^e, ``λ · (−mean_D Q(x, μ(x))) +
   mean_{S^e} ‖(μ(x) − a) / h‖² / m`` with ``λ = α / mean_D |Q(x, μ(x))|``, α = 1 (``functional.td3bc_lambda`` and
   ``functional.action_cloning``);
3. a LayerNorm after each hidden layer of Q (``make_q_network(..., layer_norm=True)``), Q starting at
   mean(r) / (1 − γ) and both networks reading observations standardised over D;
4. the selection: the evaluation whose ŵ-weighted Bellman residual on held-out rows of D is the lowest
   (``WeightedBellmanLoss.value_loss`` on them), not the last step's.

The data: a Minari pair, by default the example pair that ``python -m torchrl_wbrm.data.minari_examples --env
pendulum`` writes (20 expert episodes; 40 of uniform torques and 20 of the noisy expert), read by
``minari_replay_buffer`` in torchrl's ``MinariExperienceReplay`` layout; half of the behaviour episodes are S^b
(stage 1), the other half D (stage 2), as the recipe's ``env.minari.ratio_fraction=0.5``. The greedy actor is scored
on the env the data came from (``--env``, ``GymEnv``) against the returns of the expert and behaviour data.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile

import torch
from tensordict import TensorDict
from torchrl.data import Bounded, LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import GymEnv
from torchrl.objectives import SoftUpdate
from torchrl.record.loggers.csv import CSVLogger

from torchrl_wbrm.data import minari_replay_buffer
from torchrl_wbrm.evaluation import evaluate_returns
from torchrl_wbrm.modules import initial_q_value, make_deterministic_actor, make_q_network
from torchrl_wbrm.objectives import WeightedBellmanLoss, functional
from torchrl_wbrm.ratio import fit_density_ratio, store_density_ratio

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--quick", action="store_true", help="a few-second budget (CI)")
parser.add_argument("--seed", type=int, default=0)
parser.add_argument("--data-path", default=None, help="the Minari data path (default: a temporary folder, where the "
                    "example pair is written)")
parser.add_argument("--expert", default="examples/pendulum/expert-v0", help="the expert dataset's Minari id")
parser.add_argument("--behaviour", default="examples/pendulum/behaviour-v0", help="the behaviour dataset's Minari id")
parser.add_argument("--env", default="Pendulum-v1", help="the gymnasium id the greedy actor is scored on")
parser.add_argument("--log-dir", default=None, help="CSV logs (defaults to a temporary folder)")
args = parser.parse_args()
torch.set_num_threads(1)
torch.manual_seed(args.seed)
if args.quick:
    steps, ratio_steps, cells, eval_every, episodes = 300, 100, (64, 64), 150, 3
else:
    steps, ratio_steps, cells, eval_every, episodes = 9000, 1500, (256, 256), 1000, 10
gamma, batch_size, alpha = 0.99, 256, 1.0


def episode_returns(data: TensorDict) -> torch.Tensor:
    return torch.stack([data["next", "reward"][data["episode"] == e].sum() for e in data["episode"].unique()])


# ---- data: a Minari pair, read in torchrl's MinariExperienceReplay layout (float64 rewards cast to float32)
folder = args.data_path
if folder is None:  # the example pair, written with the package's command
    folder = tempfile.mkdtemp(prefix="wbrm_minari_agent_")
    subprocess.run([sys.executable, "-m", "torchrl_wbrm.data.minari_examples", "--env", "pendulum", "--data-path",
                    folder], check=True, stdout=subprocess.DEVNULL)
expert, behaviour = (minari_replay_buffer(dataset, batch_size, data_path=folder)[:].apply(
    lambda x: x.float() if x.is_floating_point() else x) for dataset in (args.expert, args.behaviour))
generator = torch.Generator().manual_seed(args.seed)
behaviour_episodes = behaviour["episode"].unique()
behaviour_episodes = behaviour_episodes[torch.randperm(behaviour_episodes.numel(), generator=generator)]
in_sb = torch.isin(behaviour["episode"], behaviour_episodes[: behaviour_episodes.numel() // 2])
samples_b, d = behaviour[in_sb], behaviour[~in_sb]  # S^b for stage 1, D for stage 2
held_out = torch.rand(d.shape[0], generator=generator) < 0.1  # rows of D for the selection (4.)
d_train, d_held_out = d[~held_out], d[held_out]
env = GymEnv(args.env)
action_spec = env.action_spec
if not isinstance(action_spec, Bounded):
    raise SystemExit(f"{args.env} has a {type(action_spec).__name__} action; this agent needs a Bounded (Box) one.")
obs_dim, act_dim = expert["observation"].shape[-1], expert["action"].shape[-1]

# ---- stage 1: ŵ ≈ dP^e/dP^b on S^b and S^e; stored over D as ŵ^0.25 / mean (1.)
fit = fit_density_ratio(samples_b, expert, steps=ratio_steps, batch_size=batch_size, seed=args.seed)
replay_buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(d_train.shape[0]), batch_size=batch_size)
replay_buffer.extend(d_train)
store_density_ratio(replay_buffer, ratio_network=fit.network, temper=0.25)
store_density_ratio(d_held_out, ratio_network=fit.network, temper=0.25)
print(f"stage 1: best held-out loss {fit.best_loss:.4f} at step {fit.best_step} of {fit.steps_run}")

# ---- stage 2: WeightedBellmanLoss (critic), the actor's Q term plus the S^e cloning term (2.), LayerNorm Q (3.)
loc, scale = d_train["observation"].mean(0), d_train["observation"].std(0).clamp_min(1e-6)
q = make_q_network(obs_dim, act_dim, num_cells=cells, layer_norm=True, initial_bias=initial_q_value(d_train, gamma),
                   observation_loc=loc, observation_scale=scale)
actor = make_deterministic_actor(obs_dim, action_spec, num_cells=cells, observation_loc=loc, observation_scale=scale)
loss = WeightedBellmanLoss(q, actor_network=actor, delay_value=True)
loss.make_value_estimator(gamma=gamma)
updater = SoftUpdate(loss, tau=0.05)
expert_buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(expert.shape[0]), batch_size=batch_size)
expert_buffer.extend(expert.select("observation", "action"))
half_width = (action_spec.space.high - action_spec.space.low) / 2
optimisers = {"value": torch.optim.Adam(loss.value_network_params.values(True, True), lr=1e-3),
              "actor": torch.optim.Adam(loss.actor_network_params.values(True, True), lr=1e-3)}
schedules = {"value": torch.optim.lr_scheduler.CosineAnnealingLR(optimisers["value"], T_max=steps),
             "actor": torch.optim.lr_scheduler.CosineAnnealingLR(optimisers["actor"], T_max=steps // 2)}

logger = CSVLogger(exp_name="wbrm_minari_agent", log_dir=args.log_dir or tempfile.mkdtemp(prefix="wbrm_agent_"))
best = (float("inf"), None, 0)
for step in range(1, steps + 1):
    batch = replay_buffer.sample()
    loss_value, _ = loss.value_loss(batch)
    optimisers["value"].zero_grad()
    loss_value.backward()
    optimisers["value"].step()
    schedules["value"].step()
    if step % 2 == 0:  # TD3's delayed actor and target updates
        loss_q, figures = loss.actor_loss(batch)  # −mean_D Q(x, μ(x))
        expert_batch = expert_buffer.sample()
        cloning = functional.action_cloning(actor(expert_batch.exclude("action"))["action"], expert_batch["action"],
                                            half_width)  # (2.)
        loss_actor = functional.td3bc_lambda(alpha, figures["actor_q_abs_mean"]) * loss_q + cloning
        optimisers["actor"].zero_grad()
        loss_actor.backward()
        optimisers["actor"].step()
        schedules["actor"].step()
        updater.step()
    if step % eval_every == 0:  # (4.) keep the actor with the lowest held-out ŵ-weighted residual
        with torch.no_grad():
            residual = float(loss.value_loss(d_held_out.clone())[0])
        if residual < best[0]:
            best = (residual, loss.actor_network_params.data.clone(), step)
        logger.log_scalar("held_out_weighted_residual", residual, step=step)
        logger.log_scalar("q_mean", float(figures["actor_q_mean"]), step=step)
loss.actor_network_params.data.update_(best[1])

# ---- the score: the greedy actor on the env, against the data's own returns
result = evaluate_returns(env, actor, episodes=episodes, seed=1_000_000 + args.seed)
print(f"selected step {best[2]} (held-out weighted residual {best[0]:.4f})")
print(f"WBRM agent  return {result.mean:.1f} ± {result.half_width:.1f} ({episodes} episodes)")
print(f"expert data {episode_returns(expert).mean():.1f}   behaviour data {episode_returns(behaviour).mean():.1f}")
