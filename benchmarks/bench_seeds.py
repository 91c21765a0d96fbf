"""Seeds in one process (``seeds=[...]``) against one run per seed, and the vectorised update against a plain twin.

    python benchmarks/bench_seeds.py                          # 5 seeds, 2×64 and 2×256, small budgets
    python benchmarks/bench_seeds.py --q-steps 3000 --ratio-steps 1500   # the recipe's budgets

Everything is measured in this one invocation, with one torch thread (``OMP_NUM_THREADS=1``, ``threads=1``):

1. The whole recipe (data, stage 1, the weights over D, stage 2, every evaluation, results and plots), for each
   width ``2×W`` (``q.num_cells`` and ``q.actor_num_cells``): ``python recipes/wbrm_offline.py seeds=[0,...,4]``
   (one process) against ``python recipes/wbrm_offline.py seed=s`` for each seed, one process after another, on the
   same budget. Printed: both wall times, their ratio, and where the time goes (the multi-seed run's own timing from
   its ``results.json``; process start-up is the wall time outside the recipe's own).
2. The vectorised stage-2 update alone (:class:`torchrl_wbrm.training.seeds.SeedGroup`'s update: Q step, actor step
   with the S^e cloning term, soft target update, schedules; two steps per call, one of them an actor step) against
   a plain-PyTorch twin of the same networks and update (``torch.func.stack_module_state`` + ``functional_call`` +
   ``torch.vmap``, one fused Adam per network, ``torch._foreach_lerp_``), on the same pre-drawn batches, timed
   interleaved (``benchmarks/_timing.py``).
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _timing import compare, print_comparison, single_thread  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "recipes" / "wbrm_offline.py"


def widths(width: int) -> list[str]:
    return [f"q.num_cells=[{width},{width}]", f"q.actor_num_cells=[{width},{width}]"]


def recipe(args: list[str], run_dir: Path) -> float:
    """Wall seconds of one recipe process (start-up included)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, str(RECIPE), *args, f"hydra.run.dir={run_dir}"], cwd=run_dir.parent,
                          capture_output=True, text=True, env=env)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"recipe {' '.join(args)} failed:\n{proc.stderr[-3000:]}")
    return wall


def bench_recipe(width: int, seeds: list[int], budget: list[str], out: Path) -> dict:
    overrides = [*budget, *widths(width)]
    together_dir = out / f"w{width}_together"
    together = recipe([f"seeds=[{','.join(map(str, seeds))}]", *overrides], together_dir)
    separate, inside = 0.0, 0.0
    separate_figures = []
    for seed in seeds:
        run_dir = out / f"w{width}_seed{seed}"
        separate += recipe([f"seed={seed}", *overrides], run_dir)
        results = json.loads((run_dir / "results.json").read_text())
        inside += results["wall_seconds"]
        separate_figures.append(results["final"].get("regret"))
    results = json.loads((together_dir / "results.json").read_text())
    timing = dict(results["timing"])
    timing["process start-up and imports"] = together - results["wall_seconds"]
    return {"width": width, "together_s": together, "separate_s": separate, "ratio": together / separate,
            "separate_start_up_s": separate - inside, "timing": timing, "vectorised": results["vectorised"],
            "regret_together": results["aggregate"]["final"].get("regret", {}).get("mean"),
            "regret_separate": sum(separate_figures) / len(separate_figures) if None not in separate_figures else None}


# ---------------------------------------------------------------------- the update alone
class Twin:
    """The stage-2 update written with plain torch on the same networks: Q(x, a) and μ(x) as plain ``nn.Module``s
    (deep copies of the seeds' torchrl modules, their weights stacked by ``torch.func.stack_module_state``), called
    with ``functional_call`` under ``torch.vmap``; the same losses (ŵ-weighted squared residual against the target
    networks; −λ·Q(x, μ(x)) + the S^e cloning term, λ = α / |mean Q|), fused Adam, cosine schedules, soft update."""

    def __init__(self, group, update):
        from torch.func import functional_call, stack_module_state

        cfg = group.cfg
        self.gamma = group.trainers[0].gamma
        self.tau = cfg.q.target_tau
        self.alpha = cfg.q.expert_bc_alpha
        self.delay = cfg.q.actor_delay
        self.half_width = update.cloning.half_width if update.cloning is not None else None
        q_modules, actor_modules = [], []
        for trainer in group.trainers:
            loss = trainer.algo.loss
            q = copy.deepcopy(loss.value_network.module)
            actor = copy.deepcopy(loss.actor_network.module)
            q.load_state_dict(_state(loss.value_network_params), assign=True)
            actor.load_state_dict(_state(loss.actor_network_params), assign=True)
            q_modules.append(q)
            actor_modules.append(actor)
        self.q_base = copy.deepcopy(q_modules[0]).to("meta")
        self.actor_base = copy.deepcopy(actor_modules[0]).to("meta")
        self.q_params, self.q_buffers = stack_module_state(q_modules)
        self.actor_params, self.actor_buffers = stack_module_state(actor_modules)
        self.q_target = {k: v.detach().clone() for k, v in self.q_params.items()}
        self.actor_target = {k: v.detach().clone() for k, v in self.actor_params.items()}
        q_leaves, actor_leaves = list(self.q_params.values()), list(self.actor_params.values())
        self.q_optim = torch.optim.Adam(q_leaves, lr=cfg.q.lr, fused=True)
        self.actor_optim = torch.optim.Adam(actor_leaves, lr=cfg.q.actor_lr, fused=True)
        self.schedulers = [torch.optim.lr_scheduler.CosineAnnealingLR(o, T_max=cfg.q.steps)
                           for o in (self.q_optim, self.actor_optim)]

        def q_call(params, buffers, x, a):
            return functional_call(self.q_base, (params, buffers), (x, a))

        def actor_call(params, buffers, x):
            return functional_call(self.actor_base, (params, buffers), (x,))

        def value_loss(qp, qb, qt, at, ab, x, a, r, x2, term, w):
            with torch.no_grad():
                y = r + self.gamma * (~term).int() * q_call(qt, qb, x2, actor_call(at, ab, x2)).squeeze(-1)
            delta = q_call(qp, qb, x, a).squeeze(-1) - y
            return (w * delta.pow(2)).mean()

        def actor_loss(ap, ab, qp, qb, x, xe, ae):
            qp = {k: v.detach() for k, v in qp.items()}
            q = q_call(qp, qb, x, actor_call(ap, ab, x)).squeeze(-1)
            loss_q = -q.mean()
            lam = self.alpha / q.mean().abs().detach().clamp_min(1e-6)
            bc = ((actor_call(ap, ab, xe) - ae) / self.half_width).pow(2).mean()
            return lam * loss_q + bc

        self.value_loss = torch.vmap(value_loss)
        self.actor_loss = torch.vmap(actor_loss)

    def step(self, step: int, batch, expert=None):
        x, a = batch["observation"], batch["action"]
        r = batch["next", "reward"].squeeze(-1)
        term = batch["next", "terminated"].squeeze(-1)
        w = batch["density_ratio"].squeeze(-1)
        loss = self.value_loss(self.q_params, self.q_buffers, self.q_target, self.actor_target, self.actor_buffers,
                               x, a, r, batch["next", "observation"], term, w)
        self.q_optim.zero_grad(set_to_none=True)
        loss.sum().backward()
        self.q_optim.step()
        if step % self.delay == 0:
            loss = self.actor_loss(self.actor_params, self.actor_buffers, self.q_params, self.q_buffers, x,
                                   expert["observation"], expert["action"])
            self.actor_optim.zero_grad(set_to_none=True)
            loss.sum().backward()
            self.actor_optim.step()
            with torch.no_grad():
                for target, source in ((self.q_target, self.q_params), (self.actor_target, self.actor_params)):
                    torch._foreach_lerp_(list(target.values()), [v.detach() for v in source.values()], self.tau)
        for scheduler in self.schedulers:
            scheduler.step()


def _state(params) -> dict:
    """A TensorDictParams of ``module.<...>`` entries as the inner module's state dict."""
    return {k.split(".", 1)[1]: v.detach().clone() for k, v in params.flatten_keys(".").items()}


def bench_update(width: int, seeds: list[int], iterations: int, rounds: int) -> dict:
    import warnings

    from tests.references import tiny_lqr_config
    from torchrl_wbrm.training.seeds import SeedGroup

    cfg = tiny_lqr_config(seeds=seeds, q={"num_cells": [width, width], "actor_num_cells": [width, width],
                                          "batch_size": 256, "steps": 3000})
    with tempfile.TemporaryDirectory() as tmp:
        group = SeedGroup(cfg, tmp, progress=False)
        for trainer in group.trainers:
            trainer._build_q_buffer()
        update = group.q_update()
        twin = Twin(group, update)
        batch, _ = update.sample(1)
        _, expert = update.sample(2)
        warnings.filterwarnings("ignore", message=r"Detected call of `lr_scheduler\.step\(\)` before")

        def vectorised():
            update.step(1, batch)
            update.step(2, batch, expert)

        def plain():
            twin.step(1, batch)
            twin.step(2, batch, expert)

        out = compare({"vectorised (SeedGroup)": vectorised, "plain vmapped twin": plain},
                      yardstick="plain vmapped twin", iterations=iterations, rounds=rounds, warmup=5)
        update.close()
        for trainer in group.trainers:
            trainer.release()
    print_comparison(f"stage-2 update alone, {len(seeds)} seeds, 2x{width}, batch 256 (per call: two steps, one "
                     f"with the actor)", out, per="call", yardstick="plain vmapped twin")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--widths", type=int, nargs="+", default=[64, 256])
    parser.add_argument("--q-steps", type=int, default=300)
    parser.add_argument("--ratio-steps", type=int, default=200)
    parser.add_argument("--eval-every", type=int, default=150)
    parser.add_argument("--iterations", type=int, default=20, help="update calls per timed block")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--skip-recipe", action="store_true")
    args = parser.parse_args()
    single_thread()
    sys.path.insert(0, str(ROOT))
    seeds = list(range(args.seeds))
    print(f"torch {torch.__version__}, one thread, {os.cpu_count()} CPUs, load average "
          f"{', '.join(f'{x:.1f}' for x in os.getloadavg())}")
    for width in args.widths:
        bench_update(width, seeds, args.iterations, args.rounds)
    if args.skip_recipe:
        return
    budget = [f"q.steps={args.q_steps}", f"ratio.steps={args.ratio_steps}", f"q.eval_every={args.eval_every}",
              "threads=1"]
    print(f"\nwhole recipe, {len(seeds)} seeds: one process with seeds=[...] against {len(seeds)} processes one after "
          f"another; budget {' '.join(budget)}")
    with tempfile.TemporaryDirectory() as tmp:
        for width in args.widths:
            r = bench_recipe(width, seeds, budget, Path(tmp))
            print(f"\n  2x{width}: together {r['together_s']:.1f} s, one after another {r['separate_s']:.1f} s: "
                  f"ratio {r['ratio']:.2f}x  ({'vectorised' if r['vectorised'] else 'NOT vectorised'}; mean regret "
                  f"{r['regret_together']:.4g} together, {r['regret_separate']:.4g} apart)")
            print(f"    one after another: {r['separate_start_up_s']:.1f} s of it process start-up and imports "
                  f"({r['separate_start_up_s'] / len(seeds):.1f} s per process)")
            print("    together, where the time goes:")
            for name, seconds in r["timing"].items():
                if name != "total":
                    print(f"      {name:<30} {seconds:7.2f} s")
    print(f"\nload average at the end: {', '.join(f'{x:.1f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
