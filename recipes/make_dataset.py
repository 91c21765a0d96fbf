"""Collect an offline dataset (D, S^b, S^e) with torchrl's Collector, save it and print what it holds.

    python recipes/make_dataset.py                       # LQR exp1, seed 0
    python recipes/make_dataset.py env=mountain_car      # paper sizes: 20K expert, 100K behaviour
    python recipes/make_dataset.py env=mountain_car format=minari out=datasets/minari
        # the same data as two Minari datasets, make_dataset/mountain_car_seed0/expert-v0 and .../behaviour-v0, under
        # the Minari data path datasets/minari; read them back with env=minari (see the README, "Your own data: Minari")
    python recipes/make_dataset.py overwrite=true        # collect datasets/lqr_exp1_seed0 again, replacing it

An existing dataset at ``out`` (``format=minari``: an existing id) is refused before anything is collected, unless
``overwrite=true``; a non-empty directory that holds no dataset is always refused.

``format=minari`` writes the collections the sets are made from, as whole episodes: the expert's (S^e's episodes,
with their rewards and next observations) and the behaviour's (D's and S^b's episodes together). MountainCar's
datasets record ``MountainCarContinuous-v0`` as their env; the LQR systems are not gymnasium envs, so theirs record
the spaces only (evaluate them with this project's LQR envs).

The same recipe is installed as the ``wbrm-make-dataset`` command: the Hydra app is
:func:`torchrl_wbrm.cli.make_dataset`, its config ``configs/make_dataset.yaml``.
"""
from torchrl_wbrm.cli import make_dataset as main

if __name__ == "__main__":
    main()
