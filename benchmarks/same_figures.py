"""Do the speed changes leave the recipe's figures unchanged? Runs the trainer three times in this process:

1. ``old``: every shortcut off (the TensorDict/``to_module`` loss paths, torchrl's ``SoftUpdate``, the replay
   buffers' own ``sample()``, torchrl's ``EnvBase.rollout``, the for-loop Adam);
2. ``new, for-loop Adam``: the shortcuts on, Adam as in ``old``;
3. ``new``: as the recipe runs now (fused Adam).

    python benchmarks/same_figures.py                       # a shortened default recipe (ratio 300, Q 600 steps)
    python benchmarks/same_figures.py ratio.steps=1500 q.steps=3000

Printed: the final figures of each run and whether 1 and 2 are bitwise equal (they should be: the shortcuts compute
the same numbers) and how far 3 moves from them (fused Adam rounds in another order).
"""
from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, os.path.dirname(__file__))
from _old_paths import old_paths  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def run(overrides, *, shortcuts: bool, fused: bool, run_dir: Path) -> dict:
    from hydra import compose, initialize_config_dir

    from torchrl_wbrm.configs import CONFIG_DIR
    from torchrl_wbrm.training import WBRMTrainer, register_configs

    register_configs()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("wbrm_offline", overrides=["logger=none", "plots=false", *overrides])
    with old_paths(shortcuts=shortcuts, fused=fused):
        trainer = WBRMTrainer(cfg, run_dir, progress=False)
        return trainer.run()["final"]


def main(argv=None):
    overrides = list(sys.argv[1:] if argv is None else argv) or ["ratio.steps=300", "q.steps=600", "q.eval_every=300"]
    finals = {}
    with tempfile.TemporaryDirectory() as tmp:
        for i, (name, shortcuts, fused) in enumerate((("old", False, False), ("new, for-loop Adam", True, False),
                                                      ("new", True, True))):
            finals[name] = run(overrides, shortcuts=shortcuts, fused=fused, run_dir=Path(tmp) / str(i))
    keys = [k for k in ("regret", "return", "q_error_expert", "q_error_behaviour", "held_out_bellman_residual")
            if k in finals["old"]]
    print(f"final figures ({' '.join(overrides)}):")
    for name, final in finals.items():
        print(f"  {name:<20} " + "  ".join(f"{k} {final[k]:.10g}" for k in keys))
    same = all(finals["old"][k] == finals["new, for-loop Adam"][k] for k in keys)
    print(f"  old == new with the for-loop Adam, bit for bit: {same}")
    print("  new (fused Adam) - old: " + "  ".join(f"{k} {finals['new'][k] - finals['old'][k]:+.3g}" for k in keys))


if __name__ == "__main__":
    main()
