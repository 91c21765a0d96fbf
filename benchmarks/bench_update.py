"""The WBRM updates against hand-written plain-PyTorch twins of the same networks, timed interleaved.

    python benchmarks/bench_update.py                 # eager, one torch thread
    python benchmarks/bench_update.py --device cuda

Each comparison builds the project's update exactly as the trainer does (``build_algo`` on a default
``WBRMConfig`` with the LQR task's defaults filled in, as the trainer fills them; the ratio loss and optimiser as ``WBRMTrainer._setup_ratio``) and a twin written with plain torch on
deep copies of the *same* modules (the torchrl ``MLP``s, ``BoundedTanh``, ``BoundedRatio``) from the same initial
weights, on the same batch:

* critic step: ``WeightedBellmanLoss.value_loss`` + backward + Adam + ``SoftUpdate`` vs the twin's
  ``w·(Q(x,a) − r − γ(1−term)Q'(x', μ'(x')))²`` mean + backward + ``torch.optim.Adam`` + a ``lerp_`` loop;
* full step: the trainer's step (Q every step; actor and targets every ``q.actor_delay = 2`` steps) vs the twin's
  (its actor loss ``−Q(x, μ(x)).mean()`` backpropagates through Q as CleanRL's TD3 does);
* ratio step: ``RobustDensityRatioLoss`` + backward + gradient clipping + Adam vs ``mean_b w^{3/2} − 3 mean_e
  w^{1/2}`` by hand;
* each also "with sampling": the trainer's own draw from the replay buffer (``BufferBatches``, ``PairedSampler``:
  the buffer's own indices, gathered into preallocated tensors) against ``torch.randint`` indexing of plain tensors.

Printed: median time per step over rounds and the median over rounds of the ratio to the twin (same round).
"""
from __future__ import annotations

import argparse
import copy
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(__file__))
from _timing import compare, print_comparison, single_thread  # noqa: E402

from torchrl_wbrm.data import OfflineDatasets, make_replay_buffer  # noqa: E402
from torchrl_wbrm.algos import AlgoContext, adam_options, build_algo  # noqa: E402
from torchrl_wbrm.algos.base import descend  # noqa: E402
from torchrl_wbrm.data.sampling import BufferBatches, PairedSampler  # noqa: E402
from torchrl_wbrm.data.tasks import get_task  # noqa: E402
from torchrl_wbrm.modules import DensityRatioNetwork  # noqa: E402
from torchrl_wbrm.objectives import RobustDensityRatioLoss  # noqa: E402
from torchrl_wbrm.objectives._fast import ForeachSoftUpdate  # noqa: E402
from torchrl_wbrm.training.config import WBRMConfig, resolve_defaults  # noqa: E402
from torchrl.data import Bounded  # noqa: E402
from tensordict import TensorDict  # noqa: E402


def lqr_like_data(n: int, device, seed: int = 0) -> TensorDict:
    """Transitions with the keys and dtypes of the recipe's LQR D (2-d state and action), weights included."""
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(n, 2, generator=g)
    act = torch.randn(n, 2, generator=g)
    false = torch.zeros(n, 1, dtype=torch.bool)
    td = TensorDict(
        {
            "observation": obs, "action": act, "episode": torch.arange(n) // 20, "step_count": torch.zeros(n, 1, dtype=torch.int64),
            "done": false, "terminated": false.clone(), "truncated": false.clone(),
            "density_ratio": torch.rand(n, 1, generator=g) + 0.5,
            "next": {"observation": 0.5 * obs + 0.5 * act, "reward": 8 + torch.rand(n, 1, generator=g),
                     "done": false.clone(), "terminated": false.clone(), "truncated": false.clone(),
                     "step_count": torch.ones(n, 1, dtype=torch.int64)},
        },
        batch_size=[n],
    )
    return td


def project_q(cfg: WBRMConfig, device):
    """``algo=wbrm`` built as the trainer builds it, its task holding LQR-like data (S^e feeds the expert cloning)."""
    data = lqr_like_data(2_000, torch.device("cpu"), seed=2)
    task = get_task(cfg.env).attach(OfflineDatasets.from_tensordicts(
        data, data.select("observation", "action"), data.select("observation", "action")))
    spec = Bounded(-5.0, 5.0, (2,), device=device)
    ctx = AlgoContext(cfg=cfg, observation_dim=2, action_dim=2, action_spec=spec, gamma=0.9, q_initial_bias=85.0,
                      device=device, task=task)
    return build_algo("wbrm", ctx)


class TwinQ:
    """The same update in plain torch, on deep copies of the algo's modules (same initial weights)."""

    def __init__(self, algo, gamma: float, tau: float, lr: float, actor_lr: float, actor_delay: int):
        loss = algo.loss
        with loss.value_network_params.to_module(loss.value_network):
            self.q = copy.deepcopy(loss.value_network.module)
        with loss.actor_network_params.to_module(loss.actor_network):
            self.actor = copy.deepcopy(loss.actor_network.module)
        self.q_target, self.actor_target = copy.deepcopy(self.q), copy.deepcopy(self.actor)
        for p in (*self.q_target.parameters(), *self.actor_target.parameters()):
            p.requires_grad_(False)
        self.q_opt = torch.optim.Adam(self.q.parameters(), lr=lr)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=actor_lr)
        self.online = [*self.q.parameters(), *self.actor.parameters()]
        self.target = [*self.q_target.parameters(), *self.actor_target.parameters()]
        self.gamma, self.tau, self.actor_delay = gamma, tau, actor_delay

    def soft_update(self):
        with torch.no_grad():
            for t, p in zip(self.target, self.online):
                t.lerp_(p, self.tau)

    def critic(self, obs, act, rew, term, next_obs, w):
        q = self.q(obs, act).squeeze(-1)
        with torch.no_grad():
            next_q = self.q_target(next_obs, self.actor_target(next_obs)).squeeze(-1)
            y = rew.squeeze(-1) + self.gamma * (1 - term.squeeze(-1).float()) * next_q
        loss = (w.squeeze(-1) * (q - y).pow(2)).mean()
        self.q_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.q_opt.step()
        return loss.detach()

    def critic_step(self, batch):
        loss = self.critic(*batch)
        self.soft_update()
        return loss

    def full_step(self, batch, i):
        loss = self.critic(*batch)
        if i % self.actor_delay == 0:
            actor_loss = -self.q(batch[0], self.actor(batch[0])).mean()
            self.actor_opt.zero_grad(set_to_none=True)
            actor_loss.backward()
            self.actor_opt.step()
            self.soft_update()
        return loss


def twin_tensors(td: TensorDict):
    return (td["observation"], td["action"], td["next", "reward"], td["next", "terminated"], td["next", "observation"],
            td["density_ratio"])


def q_comparisons(cfg, device, iterations, rounds):
    data = lqr_like_data(18_000, device)
    algo = project_q(cfg, device)
    twin = TwinQ(algo, 0.9, cfg.q.target_tau, cfg.q.lr, cfg.q.actor_lr, cfg.q.actor_delay)
    buffer = make_replay_buffer(data, batch_size=cfg.q.batch_size)
    batch = buffer.sample().to(device)
    tensors = tuple(t.to(device) for t in twin_tensors(batch))
    plain = tuple(t.to(device) for t in twin_tensors(data))
    n = data.shape[0]
    counter = {"ours": 0, "twin": 0}

    def ours_critic():
        return critic_step(algo, cfg, batch)

    def twin_critic():
        return twin.critic_step(tensors)

    def ours_full():
        counter["ours"] += 1
        return algo.step(batch, counter["ours"])

    def twin_full():
        counter["twin"] += 1
        return twin.full_step(tensors, counter["twin"])

    batches = BufferBatches(buffer, device=device)  # what the trainer samples with

    def ours_sampled():
        counter["ours"] += 1
        return algo.step(batches.sample(), counter["ours"])

    def twin_sampled():
        counter["twin"] += 1
        idx = torch.randint(n, (cfg.q.batch_size,), device=device)
        return twin.full_step(tuple(t[idx] for t in plain), counter["twin"])

    sync = torch.cuda.synchronize if device.type == "cuda" else None
    r = compare({"twin (plain torch)": twin_critic, "WeightedBellmanLoss": ours_critic},
                yardstick="twin (plain torch)", iterations=iterations, rounds=rounds, sync=sync)
    print_comparison("critic step: value_loss + backward + Adam + SoftUpdate, batch 256, 2x256 networks", r,
                     yardstick="twin (plain torch)")
    r2 = compare({"twin (plain torch)": twin_full, "algo.step": ours_full},
                 yardstick="twin (plain torch)", iterations=iterations, rounds=rounds, sync=sync)
    print_comparison("full step: Q, actor every 2nd step, targets (fixed batch)", r2, yardstick="twin (plain torch)")
    r3 = compare({"twin (randint indexing)": twin_sampled, "BufferBatches.sample + algo.step": ours_sampled},
                 yardstick="twin (randint indexing)", iterations=iterations, rounds=rounds, sync=sync)
    print_comparison("full step with sampling from the replay buffer", r3, yardstick="twin (randint indexing)")
    return {"critic": r, "full": r2, "full_sampled": r3}


def critic_step(algo, cfg, batch):
    """One Q step as the algo takes it (value loss, Adam), then the target update, without the actor."""
    loss = algo.loss
    if not hasattr(algo, "_bench_updater"):
        algo._bench_updater = ForeachSoftUpdate(loss, tau=cfg.q.target_tau)  # the updater the algos build
    value, _ = loss.value_loss(batch)
    descend(value, algo.optimisers["value"], cfg.q.grad_clip)
    algo._bench_updater.step()
    return value.detach()


def ratio_comparisons(cfg, device, iterations, rounds):
    rc = cfg.ratio
    net = DensityRatioNetwork(2, 2, bounds=tuple(rc.bounds), parameterisation=rc.parameterisation,
                              num_cells=rc.num_cells).to(device)
    twin_head = copy.deepcopy(net.module)
    loss = RobustDensityRatioLoss(net, alpha=rc.alpha)
    params = list(loss.parameters())
    opt = torch.optim.Adam(params, lr=rc.lr, weight_decay=rc.weight_decay, **adam_options(params))  # as the trainer
    twin_opt = torch.optim.Adam(twin_head.parameters(), lr=rc.lr)
    data = lqr_like_data(18_000, device).select("observation", "action")
    expert = lqr_like_data(18_000, device, seed=1).select("observation", "action")
    sampler = PairedSampler(make_replay_buffer(data), make_replay_buffer(expert), rc.batch_size, device=device)
    batch = sampler.sample().to(device)
    b = (batch["behaviour", "observation"], batch["behaviour", "action"])
    e = (batch["expert", "observation"], batch["expert", "action"])
    plain_b = tuple(t.to(device) for t in (data["observation"], data["action"]))
    plain_e = tuple(t.to(device) for t in (expert["observation"], expert["action"]))

    def ours(batch):
        out = loss(batch)
        value = out["loss_density_ratio"]
        opt.zero_grad(set_to_none=True)
        value.backward()
        torch.nn.utils.clip_grad_norm_(loss.parameters(), rc.grad_clip)
        opt.step()
        return value.detach()

    def twin(b, e):
        wb, we = twin_head(*b).squeeze(-1), twin_head(*e).squeeze(-1)
        value = wb.pow(1.5).mean() - 3 * we.pow(0.5).mean()
        twin_opt.zero_grad(set_to_none=True)
        value.backward()
        torch.nn.utils.clip_grad_norm_(twin_head.parameters(), rc.grad_clip)
        twin_opt.step()
        return value.detach()

    def twin_sampled():
        ib = torch.randint(plain_b[0].shape[0], (rc.batch_size,), device=device)
        ie = torch.randint(plain_e[0].shape[0], (rc.batch_size,), device=device)
        return twin(tuple(t[ib] for t in plain_b), tuple(t[ie] for t in plain_e))

    sync = torch.cuda.synchronize if device.type == "cuda" else None
    r = compare({"twin (plain torch)": lambda: twin(b, e), "RobustDensityRatioLoss": lambda: ours(batch)},
                yardstick="twin (plain torch)", iterations=iterations, rounds=rounds, sync=sync)
    print_comparison("ratio step: loss + backward + clip + Adam, batch 512 + 512, 2x128 network", r,
                     yardstick="twin (plain torch)")
    r2 = compare({"twin (randint indexing)": twin_sampled,
                  "PairedSampler.sample + step": lambda: ours(sampler.sample())},
                 yardstick="twin (randint indexing)", iterations=iterations, rounds=rounds, sync=sync)
    print_comparison("ratio step with sampling", r2, yardstick="twin (randint indexing)")
    return {"ratio": r, "ratio_sampled": r2}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--iterations", type=int, default=50)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--only", choices=("q", "ratio"), default=None)
    args = parser.parse_args(argv)
    single_thread()
    device = torch.device(args.device)
    torch.manual_seed(0)
    cfg = resolve_defaults(WBRMConfig())  # the env's defaults filled in, as the trainer fills them
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), device {device}")
    if args.only in (None, "q"):
        q_comparisons(cfg, device, args.iterations, args.rounds)
    if args.only in (None, "ratio"):
        ratio_comparisons(cfg, device, args.iterations, args.rounds)


if __name__ == "__main__":
    main()
