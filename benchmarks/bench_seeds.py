"""Five seeds two ways: one after another in one process (``seeds=[...]``), and one process per seed; and what
vectorising their stage-2 update under ``torch.vmap`` would save.

    python benchmarks/bench_seeds.py                          # 5 seeds, 2×64 and 2×256, small budgets
    python benchmarks/bench_seeds.py --q-steps 3000 --ratio-steps 1500 --eval-every 500   # the recipe's budgets
    python benchmarks/bench_seeds.py --q-steps 3000 --ratio-steps 1500 --eval-every 500 --update   # and vmap

Everything is measured in this one invocation, with one torch thread (``OMP_NUM_THREADS=1``, ``threads=1``), for each
width ``2×W`` (``q.num_cells`` and ``q.actor_num_cells``) on the same budget:

1. **one after another**: ``python recipes/wbrm_offline.py seeds=[0,...,4]``, one process, each seed's run after
   the other's (:func:`~torchrl_wbrm.training.seeds.run_seeds`);
2. **separate processes**: ``python recipes/wbrm_offline.py seed=s`` for each seed, one process after another.

The yardstick is (1): every wall time (process start-up included) is printed with its ratio to it, and where the
one-process run's time goes (its own ``results.json`` timing). Each seed's final regret of (1) is compared with
(2)'s.

``--update`` adds, for each width, the cost of the five seeds' stage-2 update vectorised: the same five seeds'
trainers (stage 1 run on a small budget), and their update step (the wbrm algo's ``value_loss``, backward, Adam;
every ``q.actor_delay`` steps ``actor_loss`` with the S^e cloning term, backward, Adam and the soft target update)
timed interleaved, on the same five batches (D's draw left out, as both sides make it per seed):

3. **update, one after another**: each seed's own ``algo.step`` in turn;
4. **update, vectorised**: the five losses' parameters stacked (``TensorDict.from_modules``), the loss's public
   ``value_loss`` and ``actor_loss`` called under ``torch.vmap`` with ``params.to_module(loss)``, one backward of
   the sum, fused Adam over the stacked tensors (element-wise, so per seed), one ``_foreach_lerp_`` for the
   targets; the cloning term is ``ExpertCloning``'s maths on each seed's own S^e draw. Its first step's losses are
   checked against (3)'s (same parameters, batches and S^e draws).

Then the share of a run's wall time spent in the update: one seed trained in this process on the budget given, its
``algo.step`` timed. A vectorised group would take ``W - 5·U·(1 - r)`` seconds where the one-process run takes
``W``, with ``U`` one seed's update seconds and ``r`` the update's ratio (4)/(3): printed as the projected ratio.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "recipes" / "wbrm_offline.py"
_ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}


def widths(width: int) -> list[str]:
    return [f"q.num_cells=[{width},{width}]", f"q.actor_num_cells=[{width},{width}]"]


def _timed(command: list[str], cwd: Path) -> float:
    """Wall seconds of one process (start-up included)."""
    start = time.perf_counter()
    proc = subprocess.run(command, cwd=cwd, capture_output=True, text=True, env=_ENV)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{proc.stderr[-3000:]}")
    return wall


def recipe(args: list[str], run_dir: Path) -> float:
    return _timed([sys.executable, str(RECIPE), *args, f"hydra.run.dir={run_dir}"], run_dir.parent)


def _final(run_dir: Path, seed: int | None = None) -> dict:
    path = run_dir / "results.json" if seed is None else run_dir / f"seed{seed}" / "results.json"
    return json.loads(path.read_text())


def bench(width: int, seeds: list[int], budget: list[str], out: Path) -> dict:
    overrides = [*budget, *widths(width)]
    listed = f"seeds=[{','.join(map(str, seeds))}]"
    walls, timing, regrets = {}, {}, {}
    name = "one after another"
    walls[name] = recipe([listed, *overrides], out / f"w{width}_together")
    results = _final(out / f"w{width}_together")
    timing[name] = {**results["timing"], "process start-up and imports": walls[name] - results["wall_seconds"]}
    regrets[name] = [r["final"].get("regret") for r in results["runs"]]
    walls["separate processes"], inside, regrets["separate processes"] = 0.0, 0.0, []
    for seed in seeds:
        run_dir = out / f"w{width}_seed{seed}"
        walls["separate processes"] += recipe([f"seed={seed}", *overrides], run_dir)
        results = _final(run_dir)
        inside += results["wall_seconds"]
        regrets["separate processes"].append(results["final"].get("regret"))
    return {"width": width, "walls": walls, "timing": timing, "regrets": regrets,
            "separate_start_up_s": walls["separate processes"] - inside}


def _prepared(width: int, budget: list[str]):
    """The recipe's config with ``budget`` at width ``2×width``, prepared (the trainers are given ``logger=None``)."""
    from omegaconf import OmegaConf

    from torchrl_wbrm.training.config import WBRMConfig, prepare_config

    overrides = [o for o in [*budget, *widths(width)] if not o.startswith("logger.")]
    return prepare_config(OmegaConf.merge(OmegaConf.structured(WBRMConfig), OmegaConf.from_dotlist(overrides)))


def trainers_after_stage1(width: int, seeds: list[int], budget: list[str], out: Path) -> list:
    """The seeds' trainers, built as ``run_seeds`` builds them and run through stage 1 (``run(until=0)``)."""
    from torchrl_wbrm.training.trainer import WBRMTrainer

    prepared = _prepared(width, budget)
    trainers = []
    for seed in seeds:
        trainer = WBRMTrainer(prepared.for_seed(seed), out / f"w{width}_update_seed{seed}", progress=False,
                              logger=None)
        trainer.run(until=0)
        trainers.append(trainer)
    return trainers


def vectorised_update(trainers: list):
    """``(update, stacked)``: ``update(batches, step, rng_states=None)``, the trainers' stage-2 update under
    ``torch.vmap`` over their stacked parameters ``stacked`` (deep copies: the trainers' own are left alone).
    ``rng_states``: each seed's generator state, set before its S^e draw."""
    import copy

    import torch
    from tensordict import TensorDict

    from torchrl_wbrm.objectives.functional import action_cloning, td3bc_lambda

    qc = trainers[0].cfg.q
    losses = [copy.deepcopy(t.algo.loss) for t in trainers]
    template = losses[0]  # its default path: the network calls read the stacked slices params.to_module puts in
    stacked = TensorDict.from_modules(*losses, as_module=True, lock=False)
    value = list(stacked["value_network_params"].values(True, True))
    actor = list(stacked["actor_network_params"].values(True, True))
    sources, targets = [], []  # the soft update's pairs: every trained tensor of Q and the actor, and its target
    for network in ("value_network_params", "actor_network_params"):
        for key, source in stacked[network].items(True, True):
            if source.requires_grad:
                sources.append(source)
                targets.append(stacked["target_" + network][key])
    value_adam = torch.optim.Adam(value, lr=qc.lr, fused=True)
    actor_adam = torch.optim.Adam(actor, lr=qc.actor_lr, fused=True)
    clonings = [t.algo.cloning for t in trainers]
    network = template.actor_network

    def value_loss(params, batch):
        with params.to_module(template):
            return template.value_loss(batch)[0]

    def actor_loss(params, batch, expert):
        with params.to_module(template):
            loss, figures = template.actor_loss(batch)
        with params["actor_network_params"].to_module(network):
            mu = network(expert.select(*network.in_keys))["action"]
        cloning = clonings[0]
        return td3bc_lambda(cloning.alpha, figures["actor_q_abs_mean"]) * loss + action_cloning(
            mu, expert["action"], cloning.half_width)

    values = torch.vmap(value_loss, (0, 0), randomness=template.vmap_randomness)
    actors = torch.vmap(actor_loss, (0, 0, 0), randomness=template.vmap_randomness)

    def update(batches, step: int, rng_states=None):
        batch = torch.stack(batches)
        loss_value = values(stacked, batch)
        value_adam.zero_grad(set_to_none=True)
        loss_value.sum().backward()
        value_adam.step()
        out = {"loss_value": loss_value.detach()}
        if step % qc.actor_delay == 0:
            experts = []
            for k, cloning in enumerate(clonings):  # each seed's own S^e draw, from its own generator state
                if rng_states is not None:
                    torch.set_rng_state(rng_states[k])
                experts.append(cloning.batches().sample().clone())
            loss_actor = actors(stacked, batch, torch.stack(experts))
            actor_adam.zero_grad(set_to_none=True)
            loss_actor.sum().backward()
            actor_adam.step()
            with torch.no_grad():
                torch._foreach_lerp_(targets, sources, qc.target_tau)
            out["loss_actor"] = loss_actor.detach()
        return out

    return update, stacked


def bench_update(width: int, seeds: list[int], budget: list[str], out: Path, rounds: int) -> dict:
    """Five seeds' stage-2 update, one after another and vectorised, timed interleaved (median over rounds)."""
    import torch

    sys.path.insert(0, str(Path(__file__).parent))
    from _timing import compare

    trainers = trainers_after_stage1(width, seeds, [*budget, "ratio.steps=10", "ratio.eval_every=10"], out)
    batches = [t.q_buffer.sample() for t in trainers]
    update, _ = vectorised_update(trainers)
    # the first step both ways, from the same parameters, batches and S^e draws: the same losses
    states = [torch.get_rng_state() for _ in trainers]
    vectorised = update([b.clone() for b in batches], 2, rng_states=states)
    for k, (trainer, batch) in enumerate(zip(trainers, batches)):
        torch.set_rng_state(states[k])
        alone = trainer.algo.step(batch.clone(), 2)
        for key in ("loss_value", "loss_actor"):
            torch.testing.assert_close(vectorised[key][k], alone[key], rtol=1e-4, atol=1e-5)
    counter = {"one after another": 0, "vectorised": 0}

    def one_after_another():
        counter["one after another"] += 1
        for trainer, batch in zip(trainers, batches):
            trainer.algo.step(batch, counter["one after another"])

    def vectorised_step():
        counter["vectorised"] += 1
        update(batches, counter["vectorised"])

    timed = compare({"one after another": one_after_another, "vectorised": vectorised_step},
                    yardstick="one after another", iterations=20, rounds=rounds)
    return {"width": width, "update": timed, "share": update_share(width, budget, out)}


def update_share(width: int, budget: list[str], out: Path) -> dict:
    """One seed's run in this process on ``budget``: its wall time (set-up and both stages) and the seconds inside
    ``algo.step``."""
    import time

    from torchrl_wbrm.training.trainer import WBRMTrainer

    prepared = _prepared(width, budget)
    start = time.perf_counter()
    trainer = WBRMTrainer(prepared.for_seed(0), out / f"w{width}_share", progress=False, logger=None)
    step, spent = trainer.algo.step, [0.0, 0]

    def timed_step(batch, i):
        t0 = time.perf_counter()
        figures = step(batch, i)
        spent[0] += time.perf_counter() - t0
        spent[1] += 1
        return figures

    trainer.algo.step = timed_step
    trainer.run()
    wall = time.perf_counter() - start
    return {"run_s": wall, "update_s": spent[0], "steps": spent[1]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--widths", type=int, nargs="+", default=[64, 256])
    parser.add_argument("--q-steps", type=int, default=300)
    parser.add_argument("--ratio-steps", type=int, default=200)
    parser.add_argument("--eval-every", type=int, default=150)
    parser.add_argument("--update", action="store_true", help="also time the stage-2 update vectorised")
    parser.add_argument("--no-runs", action="store_true", help="skip the whole runs (with --update)")
    parser.add_argument("--rounds", type=int, default=15, help="--update's rounds of 20 steps each way")
    args = parser.parse_args()
    seeds = list(range(args.seeds))
    budget = [f"q.steps={args.q_steps}", f"ratio.steps={args.ratio_steps}", f"q.eval_every={args.eval_every}",
              "threads=1", "logger.backend="]
    print(f"{len(seeds)} seeds two ways, one torch thread, {os.cpu_count()} CPUs, load average "
          f"{', '.join(f'{x:.1f}' for x in os.getloadavg())}; budget {' '.join(budget)}")
    yardstick = "one after another"
    with tempfile.TemporaryDirectory() as tmp:
        for width in args.widths:
            if args.update:
                u = bench_update(width, seeds, budget, Path(tmp), args.rounds)
                ratio, share = u["update"]["vectorised"]["ratio"], u["share"]
                print(f"\n2x{width}  stage-2 update of {len(seeds)} seeds (ratio: median over rounds of time / time "
                      f"one after another)")
                for name, t in u["update"].items():
                    print(f"  {name:<20} {t['median_s'] * 1e3:8.2f} ms a step of {len(seeds)} seeds   "
                          f"ratio {t['ratio']:.2f}x")
                seconds = share["update_s"] * len(seeds)
                print(f"  one seed's run in this process: {share['run_s']:.1f} s, of it {share['update_s']:.1f} s "
                      f"in algo.step ({share['steps']} steps, {share['update_s'] / share['run_s']:.0%})")
            if args.no_runs:
                if args.update:
                    runs = share["run_s"] * len(seeds)
                    print(f"  projected whole-run ratio, vectorised / one after another: "
                          f"{(runs - seconds * (1 - ratio)) / runs:.2f}x (from the one seed's run, imports left out)")
                continue
            r = bench(width, seeds, budget, Path(tmp))
            print(f"\n2x{width}  (ratio: wall time / wall time of {yardstick!r} in one process)")
            for name, wall in r["walls"].items():
                mean = sum(r["regrets"][name]) / len(seeds)
                print(f"  {name:<20} {wall:7.1f} s   ratio {wall / r['walls'][yardstick]:.2f}x   "
                      f"mean regret {mean:.6g}")
            exact = {name: r["regrets"][name] == r["regrets"]["separate processes"] for name in r["timing"]}
            print(f"  each seed's regret equal to its separate run's: "
                  f"{', '.join(f'{k}: {v}' for k, v in exact.items())}")
            print(f"  separate processes: {r['separate_start_up_s']:.1f} s of it process start-up and imports")
            if args.update:
                one = r["walls"][yardstick]
                print(f"  vectorised (projected)  {one - seconds * (1 - ratio):7.1f} s   ratio "
                      f"{(one - seconds * (1 - ratio)) / one:.2f}x   (= one after another - {len(seeds)} x "
                      f"{share['update_s']:.1f} s x (1 - {ratio:.2f}))")
            print(f"  where the time of {yardstick!r} goes:")
            for part, seconds in r["timing"][yardstick].items():
                if part != "total":
                    print(f"    {part:<30} {seconds:7.2f} s")
    print(f"\nload average at the end: {', '.join(f'{x:.1f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
