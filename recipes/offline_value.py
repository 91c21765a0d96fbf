"""The value of the policy a finished run delivered, estimated from its data alone: FQE on D (and ŵ-weighted FQE
where the run weighted D), with a 95% bootstrap interval over D's episodes. No episode of the policy is run.

    python recipes/offline_value.py outputs/wbrm_offline/lqr_exp1/<run>
    python recipes/offline_value.py <run dir> --steps 3000

The run's ``checkpoint.pt`` is read with ``torch.load(weights_only=True)`` (nothing in it runs); D is rebuilt from
the config saved in it. Nothing is written. The estimate is the quantity the run's online ``return`` reports
(:mod:`torchrl_wbrm.training.offline_value`).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch



def _plain(value, key: str = "config") -> None:
    """Refuse a saved config value that OmegaConf would resolve (``${...}``): the record is data, never evaluated."""
    if isinstance(value, dict):
        for k, v in value.items():
            _plain(v, f"{key}.{k}")
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            _plain(v, f"{key}[{i}]")
    elif isinstance(value, str) and "${" in value:
        raise ValueError(f"The checkpoint's {key} holds an interpolation ('${{...}}'), not a plain value: refused.")


def offline_value_of_run(run_dir, *, steps: int | None = None) -> tuple[dict, dict, dict]:
    """The offline value of the policy a finished run delivered, as the trainer's ``offline_value`` computes it at
    the end of the run: ``(final figures, record, run)`` where ``run`` names the env, algo, seed, step and the
    delivered step. ``run_dir/checkpoint.pt`` is read with ``torch.load(weights_only=True)``
    (:func:`~torchrl_wbrm.training.checkpoint.read_checkpoint`); the run's config is the one saved in it, and D is
    rebuilt from it (the data cache or dataset it names, or the same seed). ``steps``: FQE's steps (default the run's
    ``eval.offline_value_steps``). No policy episode is run; nothing is written to ``run_dir``."""
    from omegaconf import OmegaConf

    from torchrl_wbrm.training.checkpoint import read_checkpoint
    from torchrl_wbrm.training.config import WBRMConfig
    from torchrl_wbrm.training.trainer import WBRMTrainer

    run_dir = Path(run_dir)
    path = run_dir / "checkpoint.pt"
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist: give the directory of a finished run (one that holds its "
                                "checkpoint.pt; a multi-seed run holds one per seed, in seed_<s>/).")
    saved = read_checkpoint(path)
    if saved.get("state", {}).get("stage") != "done":
        state = saved.get("state", {})
        raise ValueError(f"{run_dir} holds an unfinished run (stage {state.get('stage')!r}, step {state.get('step')}): "
                         f"finish it (resume={run_dir}) first; its delivered policy is chosen at the end.")
    record = dict(saved["config"])
    _plain(record)
    record.pop("seeds", None)
    cfg = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(WBRMConfig), record))
    trainer = WBRMTrainer(cfg, run_dir, resume=True, logger=None, progress=False, evaluation=False)
    try:
        evaluations = [r for r in trainer.history if r["stage"] == "q"]
        delivered = evaluations[-1].get("selected_step", trainer.state["step"]) if evaluations else None
        figures, summary = trainer.offline_value(steps)
    finally:
        trainer.release()
    run = {"env": cfg.env.name, "algo": cfg.algo, "seed": cfg.seed, "step": trainer.state["step"],
           "delivered_step": delivered}
    return figures, summary, run


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir", help="a finished run's directory (holding checkpoint.pt)")
    parser.add_argument("--steps", type=int, default=None, help="FQE's steps (default: the run's eval.offline_value_steps)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    try:
        figures, record, run = offline_value_of_run(args.run_dir, steps=args.steps)
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(f"Refused (nothing was written): {err}") from None
    print(f"run {args.run_dir}: env {run['env']}  algo {run['algo']}  seed {run['seed']}  "
          f"delivered step {run['delivered_step']} of {run['step']}")
    if not figures:
        raise SystemExit(f"No estimate: {record['skipped']}.")
    print(f"quantity: {record['quantity']} ({record['episodes']} episodes of D; FQE, {record['steps']} steps)")
    weighted = {"stage2": "ŵ-weighted FQE on D (stage 2's weights)",
                "ratio": "ratio-weighted FQE on D (ŵ unshaped)"}.get(record.get("weights"), "ŵ-weighted FQE on D")
    for key, name in (("offline_value", "FQE on D"), ("offline_value_weighted", weighted)):
        if key in figures:
            print(f"{name}: {figures[key]:.4f} ± {figures[f'{key}_ci']:.4f}   "
                  f"(95% CI [{figures[f'{key}_low']:.4f}, {figures[f'{key}_high']:.4f}], over D's episodes)")
    print("The environment was not run for this estimate: no evaluation env was built and no episode of the policy was "
          "run; it reads the run's checkpoint and its data D only.")


if __name__ == "__main__":
    main()
