"""Discrete actions: ``WeightedBellmanLoss`` with TorchRL's ``QValueActor`` on CartPole-v1, against TorchRL's
``DQNLoss`` on the same offline data.

    python examples/wbrm_dqn_cartpole.py            # the full budget
    python examples/wbrm_dqn_cartpole.py --quick    # a few seconds (CI)

The offline data are made here with gymnasium: an expert (push towards the side the pole falls to, ``θ + θ̇ > 0``,
5% random actions) gives S^e; a behaviour policy (the same rule with 70% random actions) gives whole episodes, split
by episode into D (transitions) and S^b (state-actions). Stage 1 (``torchrl_wbrm.ratio``) fits ŵ ≈ dP^e/dP^b on
(observation, one-hot action) and stores it over D. Both losses then train the same Q network from the same
initialisation, with the same batches, optimiser and ``SoftUpdate``; the greedy policies are scored on fresh episodes
(``--quick`` trains ``WeightedBellmanLoss`` only).
"""
from __future__ import annotations

import argparse
import tempfile

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, OneHot, TensorDictReplayBuffer
from torchrl.modules import MLP, QValueActor
from torchrl.objectives import DQNLoss, SoftUpdate
from torchrl.record.loggers.csv import CSVLogger

from torchrl_wbrm.objectives import WeightedBellmanLoss
from torchrl_wbrm.ratio import fit_density_ratio, store_density_ratio

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--quick", action="store_true", help="a few-second budget (CI)")
parser.add_argument("--seed", type=int, default=0)
parser.add_argument("--log-dir", default=None, help="CSV logs (defaults to a temporary folder)")
args = parser.parse_args()
torch.set_num_threads(1)
torch.manual_seed(args.seed)
rng = np.random.default_rng(args.seed)
budget = (1500, 200, 10, 10) if args.quick else (10_000, 1000, 50, 100)
steps, behaviour_episodes, expert_episodes, eval_episodes = budget
env = gym.make("CartPole-v1")


def expert_action(obs: np.ndarray) -> int:
    return int(obs[2] + obs[3] > 0)  # push towards the side the pole is falling to


def collect(episodes: int, random_share: float) -> TensorDict:
    """Whole episodes of the rule above with a share of uniform random actions, as flat transitions."""
    keys = ("observation", "action", "reward", "next_observation", "terminated", "truncated", "episode")
    rows = {key: [] for key in keys}
    for episode in range(episodes):
        obs, _ = env.reset(seed=int(rng.integers(2**31)))
        done = False
        while not done:
            action = int(rng.integers(2)) if rng.random() < random_share else expert_action(obs)
            next_obs, reward, terminated, truncated, _ = env.step(action)
            for key, value in zip(rows, (obs, action, reward, next_obs, terminated, truncated, episode)):
                rows[key].append(value)
            obs, done = next_obs, terminated or truncated
    n = len(rows["action"])
    flag = lambda key: torch.as_tensor(np.array(rows[key]), dtype=torch.bool).reshape(n, 1)  # noqa: E731
    return TensorDict({
        "observation": torch.as_tensor(np.array(rows["observation"]), dtype=torch.float32),
        "action": torch.nn.functional.one_hot(torch.as_tensor(rows["action"]), 2),
        "episode": torch.as_tensor(rows["episode"]),
        ("next", "observation"): torch.as_tensor(np.array(rows["next_observation"]), dtype=torch.float32),
        ("next", "reward"): torch.as_tensor(rows["reward"], dtype=torch.float32).reshape(n, 1),
        ("next", "terminated"): flag("terminated"),
        ("next", "truncated"): flag("truncated"),
        ("next", "done"): flag("terminated") | flag("truncated"),
    }, [n])


def mean_return(policy, episodes: int) -> float:
    """Mean undiscounted return of the greedy ``policy`` over fresh episodes (seeds apart from the data's), all
    episodes stepped together so that the policy runs once per time step."""
    envs = [gym.make("CartPole-v1") for _ in range(episodes)]
    obs = np.stack([e.reset(seed=10_000 + i)[0] for i, e in enumerate(envs)])
    totals, running = np.zeros(episodes), np.ones(episodes, dtype=bool)
    while running.any():
        live = np.flatnonzero(running)
        with torch.no_grad():
            td = policy(TensorDict({"observation": torch.as_tensor(obs[live], dtype=torch.float32)}, [len(live)]))
        for i, action in zip(live, td["action"].argmax(-1).tolist()):
            obs[i], reward, terminated, truncated, _ = envs[i].step(action)
            totals[i] += reward
            running[i] = not (terminated or truncated)
    return float(totals.mean())


# ---- offline data: behaviour episodes split by episode into D and S^b; expert episodes give S^e
behaviour, expert = collect(behaviour_episodes, 0.7), collect(expert_episodes, 0.05)
in_d = behaviour["episode"] % 2 == 0
transitions, behaviour_samples = behaviour[in_d], behaviour[~in_d]
behaviour_return = behaviour["next", "reward"].sum().item() / behaviour_episodes
expert_return = expert["next", "reward"].sum().item() / expert_episodes
print(f"data: D {transitions.shape[0]} transitions, S^b {behaviour_samples.shape[0]}, S^e {expert.shape[0]}; "
      f"behaviour return {behaviour_return:.1f}, expert return {expert_return:.1f}")
replay_buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(transitions.shape[0]), batch_size=128)
replay_buffer.extend(transitions)

# ---- stage 1: ŵ on (observation, one-hot action), stored over D as "density_ratio" (ŵ^0.25, mean 1)
observation_action = ("observation", "action")
fit = fit_density_ratio(behaviour_samples.select(*observation_action).float(),
                        expert.select(*observation_action).float(), steps=300 if args.quick else 1500,
                        batch_size=256, num_cells=(64, 64), lr=3e-3, seed=args.seed)
ratio_input = replay_buffer[:].select(*observation_action).float()
store_density_ratio(replay_buffer, fit.network(ratio_input)["density_ratio"].detach(), key="density_ratio", temper=0.25)
print(f"stage 1: best held-out loss {fit.best_loss:.4f} at step {fit.best_step} of {fit.steps_run}")


def train(name: str) -> float:
    """TorchRL's offline DQN loop with the named loss; returns the greedy policy's mean return."""
    torch.manual_seed(args.seed)
    actor = QValueActor(MLP(in_features=4, out_features=2, num_cells=[64, 64]), in_keys=["observation"],
                        spec=OneHot(2))
    if name == "DQNLoss":
        loss = DQNLoss(actor, action_space="one-hot", loss_function="l2", delay_value=True)
    else:
        loss = WeightedBellmanLoss(actor, residual="squared", delay_value=True)
    loss.make_value_estimator(gamma=0.99)
    updater = SoftUpdate(loss, tau=0.01)
    optim = torch.optim.Adam(loss.value_network_params.values(True, True), lr=1e-3)
    logger = CSVLogger(exp_name=name, log_dir=log_dir)
    torch.manual_seed(args.seed + 1)  # the same batches for both losses
    for step in range(1, steps + 1):
        out = loss(replay_buffer.sample())
        value_loss = out["loss"] if name == "DQNLoss" else out["loss_value"]
        optim.zero_grad()
        value_loss.backward()
        optim.step()
        updater.step()
        if step % 100 == 0:
            logger.log_scalar("loss", value_loss.item(), step=step)
    return mean_return(actor, eval_episodes)


log_dir = args.log_dir or tempfile.mkdtemp(prefix="wbrm_cartpole_")
for name in ("WeightedBellmanLoss",) if args.quick else ("DQNLoss", "WeightedBellmanLoss"):
    print(f"{name:<20} greedy return {train(name):.1f}   (behaviour data {behaviour_return:.1f}, max 500)")
