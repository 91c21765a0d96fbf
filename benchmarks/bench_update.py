"""The WBRM updates against hand-written plain-PyTorch twins of the same networks, timed interleaved.

    python benchmarks/bench_update.py                 # eager, one torch thread, 2x64 and 2x256 networks
    python benchmarks/bench_update.py --widths 64     # one width only
    python benchmarks/bench_update.py --device cuda

The stage-2 comparisons run at each hidden width of ``--widths`` (Q and the actor both ``2 x width``; the twin at
the same width), batch 256; the ratio step at the ratio network's default width. Each builds the project's update exactly as the trainer does (``build_algo`` on a default
``WBRMConfig`` with the LQR task's defaults filled in, as the trainer fills them; the ratio loss and optimiser as ``training.parts.make_ratio_fitter``) and a twin written with plain torch on
deep copies of the *same* modules (the torchrl ``MLP``s, ``BoundedTanh``, ``BoundedRatio``) from the same initial
weights, on the same batch:

* critic step: ``WeightedBellmanLoss.value_loss`` + backward + Adam + ``SoftUpdate`` vs the twin's
  ``w·(Q(x,a) − r − γ(1−term)Q'(x', μ'(x')))²`` mean + backward + ``torch.optim.Adam`` + a ``lerp_`` loop;
* full step: the algo's step (Q every step; actor and targets every ``q.actor_delay = 2`` steps) vs the twin's. The
  default actor loss is TD3+BC's form with the expert cloning term on S^e (``q.expert_bc_alpha = 1``):
  ``λ·(−mean Q(x, μ(x))) + mean ‖(μ(x_e) − a_e)/h‖²/m`` with ``λ = α/|mean Q(x, μ(x))|``, an S^e batch drawn at each
  actor step (the twin: ``torch.randint`` indexing of S^e's tensors); the twin freezes Q's parameters for the actor's
  backward (``requires_grad_(False)``, as Spinning Up's TD3), as the loss calls Q with detached parameters;
* ratio step: ``RobustDensityRatioLoss`` + backward + gradient clipping + Adam vs ``mean_b w^{3/2} − 3 mean_e
  w^{1/2}`` by hand;
* each also "with sampling": the trainer's own draw from the replay buffer (``BufferBatches``, ``PairedSampler``:
  the buffer's own indices, gathered into preallocated tensors) against ``torch.randint`` indexing of plain tensors;
* whole stage-2 step: a ``WBRMTrainer`` (default config at that width, the LQR task's data, ŵ stored in D) running
  its own loop (``WBRMTrainer._run_stage`` with ``_q_step``: the draw from D's buffer, the algo's step, the
  learning-rate schedules, the divergence check of the step's figures, the step counter, the figures logged to the
  history every ``logger.log_every`` steps) against the twin's loop doing the same (``randint`` draws from D and S^e,
  the same update, ``CosineAnnealingLR`` schedules, the losses read and kept every ``log_every`` steps). Evaluation
  and checkpoints are left out (``eval_every`` past the run, ``checkpoint_every = 0``). Each timed call runs
  ``--iterations`` steps of the loop.

Printed: median time per step over rounds and the median over rounds of the ratio to the twin (same round).
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import math
import os
import sys
import tempfile
import warnings

import torch

sys.path.insert(0, os.path.dirname(__file__))
from _timing import compare, print_comparison, single_thread  # noqa: E402

from torchrl_wbrm.data import OfflineDatasets, make_replay_buffer  # noqa: E402
from torchrl_wbrm.algos import AlgoContext, adam_options, build_algo  # noqa: E402
from torchrl_wbrm.algos.base import descend  # noqa: E402
from torchrl_wbrm.data.sampling import BufferBatches, PairedSampler  # noqa: E402
from torchrl_wbrm.tasks import get_task  # noqa: E402
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
    """``algo=wbrm`` built as the trainer builds it, its task holding LQR-like data (S^e feeds the expert cloning),
    and the twin of it."""
    data = lqr_like_data(2_000, torch.device("cpu"), seed=2)
    task = get_task(cfg.env).attach(OfflineDatasets.from_tensordicts(
        data, data.select("observation", "action"), data.select("observation", "action")))
    spec = Bounded(-5.0, 5.0, (2,), device=device)
    ctx = AlgoContext(cfg=cfg, observation_dim=2, action_dim=2, action_spec=spec, gamma=0.9, q_initial_bias=85.0,
                      device=device, task=task)
    algo = build_algo("wbrm", ctx)
    return algo, make_twin(algo, cfg, 0.9, task.datasets.expert_samples[:], spec, device)


def make_twin(algo, cfg: WBRMConfig, gamma: float, expert: TensorDict, spec, device) -> "TwinQ":
    """The twin of ``algo``: the same networks, optimisers' settings and actor loss (S^e's tensors for its cloning
    term when ``q.expert_bc_alpha`` is set)."""
    qc = cfg.q
    cloning = dict(expert=(expert["observation"].to(device), expert["action"].to(device)), alpha=qc.expert_bc_alpha,
                   low=spec.space.low.to(device), high=spec.space.high.to(device)) if qc.expert_bc_alpha else {}
    return TwinQ(algo, gamma, qc.target_tau, qc.lr, qc.actor_lr, qc.actor_delay, batch_size=qc.batch_size, **cloning)


class TwinQ:
    """The same update in plain torch, on deep copies of the algo's modules (same initial weights).

    ``expert``: S^e's ``(observation, action)`` tensors, for the cloning term of the actor loss (``alpha``: its α;
    ``None``: no cloning term); ``low``/``high``: the action box.
    """

    def __init__(self, algo, gamma: float, tau: float, lr: float, actor_lr: float, actor_delay: int, *,
                 expert=None, alpha=None, low=None, high=None, batch_size: int = 256):
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
        self.q_params = list(self.q.parameters())
        self.online = [*self.q.parameters(), *self.actor.parameters()]
        self.target = [*self.q_target.parameters(), *self.actor_target.parameters()]
        self.gamma, self.tau, self.actor_delay = gamma, tau, actor_delay
        self.expert, self.alpha, self.batch_size = expert, alpha, batch_size
        if expert is not None:
            self.half_width = ((high - low) / 2).clamp_min(1e-6)

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

    def actor_step(self, obs):
        for p in self.q_params:
            p.requires_grad_(False)
        q = self.q(obs, self.actor(obs))
        for p in self.q_params:
            p.requires_grad_(True)
        loss = -q.mean()
        if self.expert is not None:  # TD3+BC's λ and the cloning term on an S^e batch
            i = torch.randint(self.expert[0].shape[0], (self.batch_size,))
            obs_e, act_e = self.expert[0][i], self.expert[1][i]
            bc = ((self.actor(obs_e) - act_e) / self.half_width).pow(2).mean()
            loss = self.alpha / q.detach().mean().abs().clamp_min(1e-6) * loss + bc
        self.actor_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.actor_opt.step()
        return loss.detach()

    def full_step(self, batch, i):
        loss = self.critic(*batch)
        actor_loss = None
        if i % self.actor_delay == 0:
            actor_loss = self.actor_step(batch[0])
            self.soft_update()
        return loss, actor_loss


def twin_tensors(td: TensorDict):
    return (td["observation"], td["action"], td["next", "reward"], td["next", "terminated"], td["next", "observation"],
            td["density_ratio"])


def width_of(cfg: WBRMConfig) -> str:
    return f"2x{cfg.q.num_cells[0]}" if len(set(cfg.q.num_cells)) == 1 else "x".join(map(str, cfg.q.num_cells))


def q_comparisons(cfg, device, iterations, rounds):
    data = lqr_like_data(18_000, device)
    algo, twin = project_q(cfg, device)
    w = width_of(cfg)
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
    print_comparison(f"critic step: value_loss + backward + Adam + SoftUpdate, batch {cfg.q.batch_size}, {w} networks",
                     r, yardstick="twin (plain torch)")
    r2 = compare({"twin (plain torch)": twin_full, "algo.step": ours_full},
                 yardstick="twin (plain torch)", iterations=iterations, rounds=rounds, sync=sync)
    print_comparison(f"full step: Q, actor (with the S^e cloning term) every 2nd step, targets (fixed batch), {w}", r2,
                     yardstick="twin (plain torch)")
    r3 = compare({"twin (randint indexing)": twin_sampled, "BufferBatches.sample + algo.step": ours_sampled},
                 yardstick="twin (randint indexing)", iterations=iterations, rounds=rounds, sync=sync)
    print_comparison(f"full step with sampling from the replay buffer, {w}", r3, yardstick="twin (randint indexing)")
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


def per_step(results: dict, steps: int) -> dict:
    """``results`` of calls that each ran ``steps`` steps, as times per step (the ratios unchanged)."""
    return {name: {**r, "median_s": r["median_s"] / steps, "min_s": r["min_s"] / steps} for name, r in results.items()}


def trainer_comparison(cfg: WBRMConfig, device, iterations, rounds):
    """One seed's whole stage-2 step: ``WBRMTrainer``'s own loop against the twin's loop doing the same."""
    from torchrl_wbrm.training import WBRMTrainer

    cfg = dataclasses.replace(cfg, checkpoint_every=0, plots=False, device=str(device))
    qc, log_every = cfg.q, cfg.logger.log_every
    never = 10**9  # no evaluation within the run, no last step reached
    with tempfile.TemporaryDirectory() as run_dir:
        trainer = WBRMTrainer(cfg, run_dir, progress=False)
        try:
            single_thread()  # (the trainer sets cfg.threads, 1 by default)
            trainer._build_q_buffer()  # ŵ over D (stage 1 not run: the initial ratio network's), stored in D
            trainer.state = {"stage": "q", "step": 0}
            twin = make_twin(trainer.algo, trainer.cfg, trainer.gamma, trainer.datasets.expert_samples[:],
                             trainer.action_spec, device)
            data = trainer.q_buffer[:]
            plain = tuple(t.to(device) for t in twin_tensors(data))
            n = data.shape[0]
            schedules = []
            if qc.lr_schedule == "cosine":
                schedules = [torch.optim.lr_scheduler.CosineAnnealingLR(o, T_max=qc.steps)
                             for o in (twin.q_opt, twin.actor_opt)]
            twin_state = {"step": 0, "actor_loss": None}
            twin_history = []

            def ours():
                trainer._run_stage("q", never, trainer._q_step, eval_every=never, eval_fn=lambda step: None,
                                   until=trainer.state["step"] + iterations)

            def twin_loop():
                for _ in range(iterations):
                    step = twin_state["step"] + 1
                    idx = torch.randint(n, (qc.batch_size,), device=device)
                    loss, actor_loss = twin.full_step(tuple(t[idx] for t in plain), step)
                    for schedule in schedules:
                        schedule.step()
                    twin_state["step"] = step
                    if actor_loss is not None:
                        twin_state["actor_loss"] = actor_loss
                    if step % log_every == 0:
                        figures = {"loss_value": loss.item(), "loss_actor": twin_state["actor_loss"].item()}
                        if not all(math.isfinite(v) for v in figures.values()):
                            raise FloatingPointError(f"twin diverged at step {step}: {figures}")
                        twin_history.append({"step": step, **figures})

            sync = torch.cuda.synchronize if device.type == "cuda" else None
            with warnings.catch_warnings():  # the actor's schedule steps before its optimiser at step 1
                warnings.filterwarnings("ignore", message=r"Detected call of `lr_scheduler\.step\(\)` before")
                r = compare({"twin (plain torch loop)": twin_loop, "WBRMTrainer loop": ours},
                            yardstick="twin (plain torch loop)", iterations=1, rounds=rounds, warmup=2, sync=sync)
            print_comparison(f"whole stage-2 step: WBRMTrainer._run_stage(_q_step) against the twin's loop, "
                             f"{width_of(cfg)}, batch {qc.batch_size} ({iterations} steps a call)",
                             per_step(r, iterations), yardstick="twin (plain torch loop)")
        finally:
            trainer.release()
    return {"whole_step": r}


def at_width(cfg: WBRMConfig, width: int) -> WBRMConfig:
    """``cfg`` with Q and the actor both ``2 x width``."""
    return dataclasses.replace(cfg, q=dataclasses.replace(cfg.q, num_cells=[width, width],
                                                          actor_num_cells=[width, width]))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--iterations", type=int, default=50)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--widths", type=int, nargs="+", default=[64, 256],
                        help="hidden widths of Q and the actor (2 layers each), one set of comparisons per width")
    parser.add_argument("--only", choices=("q", "ratio", "trainer"), default=None)
    args = parser.parse_args(argv)
    single_thread()
    device = torch.device(args.device)
    torch.manual_seed(0)
    base = resolve_defaults(WBRMConfig())  # the env's defaults filled in, as the trainer fills them
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), device {device}, "
          f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    results = {}
    for width in args.widths:
        cfg = at_width(base, width)
        print(f"\n=== {width_of(cfg)} networks ===")
        out = results[width] = {}
        if args.only in (None, "q"):
            out.update(q_comparisons(cfg, device, args.iterations, args.rounds))
        if args.only in (None, "trainer"):
            out.update(trainer_comparison(cfg, device, args.iterations, args.rounds))
    if args.only in (None, "ratio"):
        results["ratio"] = ratio_comparisons(base, device, args.iterations, args.rounds)
    print(f"\nload average after the run: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return results


if __name__ == "__main__":
    main()
