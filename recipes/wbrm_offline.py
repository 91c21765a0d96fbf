"""Deep Weighted Bellman Residual Minimization, offline: stage 1 fits the density ratio ŵ, stage 2 fits Q*.

    python recipes/wbrm_offline.py                                  # LQR exp1, the default (about a minute)
    python recipes/wbrm_offline.py env=lqr_exp3 seed=2
    python recipes/wbrm_offline.py seeds=[0,1,2,3,4]                # five seeds in one process (docs/guides/seeds.md)
    python recipes/wbrm_offline.py env=mountain_car q.gamma=0.99
    python recipes/wbrm_offline.py ratio.source=none                # the unweighted ablation
    python recipes/wbrm_offline.py algo=td3bc                       # a baseline on the same data (torchrl_wbrm/algos/)
    python recipes/wbrm_offline.py logger=wandb                     # offline wandb run in the run directory
    python recipes/wbrm_offline.py resume=outputs/wbrm_offline/...  # continue an interrupted run exactly

The same recipe is installed as the ``wbrm-offline`` command (and ``python -m torchrl_wbrm``): the Hydra app is
:func:`torchrl_wbrm.cli.wbrm_offline`, its config ``configs/wbrm_offline.yaml``.

Writes results.json, history.json, training_curve.png, evaluation.png, logs/ and checkpoint.pt in the run directory.
"""
from torchrl_wbrm.cli import wbrm_offline as main

if __name__ == "__main__":
    main()
