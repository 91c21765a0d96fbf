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

import torch

from torchrl_wbrm.training.offline_value import offline_value_of_run


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
    for key, name in (("offline_value", "FQE on D"), ("offline_value_weighted", "ŵ-weighted FQE on D")):
        if key in figures:
            print(f"{name}: {figures[key]:.4f} ± {figures[f'{key}_ci']:.4f}   "
                  f"(95% CI [{figures[f'{key}_low']:.4f}, {figures[f'{key}_high']:.4f}], over D's episodes)")
    print("The environment was not run for this estimate: it reads the run's checkpoint and its data D only.")


if __name__ == "__main__":
    main()
