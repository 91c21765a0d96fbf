"""Where the default ``python recipes/wbrm_offline.py`` spends its wall time.

    python benchmarks/bench_recipe.py                       # the default recipe, instrumented, in this process
    python benchmarks/bench_recipe.py q.steps=500           # any recipe override
    python benchmarks/bench_recipe.py --wall                # also time the real command as a subprocess
    python benchmarks/bench_recipe.py --flush-denormal q.steps=10   # stage 1 with denormal floats flushed to zero

The config is composed from ``configs/wbrm_offline.yaml`` exactly as the recipe does (Hydra's compose API, the same
overrides); the trainer runs unchanged, with timers wrapped around its methods:

* imports: a fresh interpreter importing what the recipe imports (hydra, torch, torchrl, torchrl_wbrm.training);
* data: collecting D, S^b and S^e (``trainer.data_seconds``); setup: the rest of the trainer's construction
  (networks, losses, evaluation samples and the exact ratio);
* stage 1: the ratio steps (``_run_stage("ratio")`` less its held-out evaluations); ratio eval: those evaluations;
* weights: ŵ over D into the Q buffer; stage 2: the Q steps (less evaluations); evaluation: ``_q_eval``;
* checkpoints: ``save_checkpoint``; results and plots: ``results()`` (writes results.json, history.json and the PNGs).
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

IMPORTS = ("import hydra, torch, torchrl; from omegaconf import OmegaConf; "
           "from torchrl_wbrm.training import WBRMTrainer, register_configs, validate_config; "
           "from torchrl_wbrm.training.logging import make_logger; "
           "from torchrl_wbrm.training.reporting import summarise")


def import_seconds() -> float:
    code = f"import time; t0 = time.perf_counter(); {IMPORTS}; print(time.perf_counter() - t0)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    return float(out.stdout.strip().splitlines()[-1])


def instrumented_run(overrides: list[str], run_dir: Path) -> tuple[dict, dict]:
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from torchrl_wbrm.configs import CONFIG_DIR
    from torchrl_wbrm.training import WBRMTrainer, register_configs
    from torchrl_wbrm.training.logging import make_logger

    register_configs()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("wbrm_offline", overrides=overrides)
    seconds: dict[str, float] = defaultdict(float)
    t0 = time.perf_counter()
    trainer = WBRMTrainer(cfg, run_dir, logger=None, progress=False)
    trainer.logger = make_logger(cfg.logger, run_dir, "bench", OmegaConf.to_container(cfg, resolve=True))
    construct = time.perf_counter() - t0
    seconds["data"] = trainer.data_seconds
    seconds["setup (networks, eval samples, exact ratio)"] = construct - trainer.data_seconds

    def timed(label, fn):
        def wrapper(*args, **kwargs):
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                seconds[label] += time.perf_counter() - start
        return wrapper

    run_stage = trainer._run_stage

    def stage(name, *args, **kwargs):
        start = time.perf_counter()
        evals_before = seconds["ratio eval"] + seconds["evaluation"] + seconds["checkpoints"]
        try:
            return run_stage(name, *args, **kwargs)
        finally:
            spent = time.perf_counter() - start
            evals = seconds["ratio eval"] + seconds["evaluation"] + seconds["checkpoints"] - evals_before
            seconds["stage 1 (ratio steps)" if name == "ratio" else "stage 2 (Q steps)"] += spent - evals

    trainer._run_stage = stage
    trainer._ratio_eval = timed("ratio eval", trainer._ratio_eval)
    trainer._q_eval = timed("evaluation", trainer._q_eval)
    trainer._build_q_buffer = timed("weights over D", trainer._build_q_buffer)
    trainer.save_checkpoint = timed("checkpoints", trainer.save_checkpoint)
    trainer.results = timed("results and plots", trainer.results)
    t1 = time.perf_counter()
    results = trainer.run()
    seconds["run (total)"] = time.perf_counter() - t1
    seconds["construct (total)"] = construct
    return dict(seconds), results


PARTS = ["data", "setup (networks, eval samples, exact ratio)", "stage 1 (ratio steps)", "ratio eval", "weights over D",
         "stage 2 (Q steps)", "evaluation", "checkpoints", "results and plots"]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--wall", action="store_true", help="also time `python recipes/wbrm_offline.py` itself")
    parser.add_argument("--flush-denormal", action="store_true",
                        help="torch.set_flush_denormal(True) first (is a part slowed by denormal floats?)")
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_args(argv)
    if args.flush_denormal:
        import torch

        torch.set_flush_denormal(True)
    imports = import_seconds()
    with tempfile.TemporaryDirectory() as tmp:
        seconds, results = instrumented_run(args.overrides, Path(tmp) / "run")
    order = PARTS
    total = imports + seconds["construct (total)"] + seconds["run (total)"]
    print(f"\nthe default recipe{' with ' + ' '.join(args.overrides) if args.overrides else ''}: wall-time breakdown")
    print(f"  {'imports (fresh interpreter)':<46} {imports:7.2f} s")
    for key in order:
        print(f"  {key:<46} {seconds.get(key, 0.0):7.2f} s")
    rest = total - imports - sum(seconds.get(k, 0.0) for k in order)
    print(f"  {'other (loop bookkeeping, logging)':<46} {rest:7.2f} s")
    print(f"  {'total':<46} {total:7.2f} s")
    final = results.get("final", {})
    print(f"  figures: regret {final.get('regret', float('nan')):.4f}, return {final.get('return', float('nan')):.4f}, "
          f"q_error_expert {final.get('q_error_expert', float('nan')):.4f}")
    if args.wall:
        with tempfile.TemporaryDirectory() as tmp:
            start = time.perf_counter()
            subprocess.run([sys.executable, "recipes/wbrm_offline.py", f"hydra.run.dir={tmp}/run", *args.overrides],
                           cwd=ROOT, check=True, capture_output=True)
            print(f"  `python recipes/wbrm_offline.py` as a subprocess: {time.perf_counter() - start:.2f} s wall")


if __name__ == "__main__":
    os.environ.setdefault("TQDM_DISABLE", "1")
    main()
