"""Offline datasets, read and written: collection with torchrl's Collector, the D / S^b / S^e split, replay
buffers, save/load."""
from torchrl_wbrm.data.datasets import (
    OfflineDatasets,
    collect_transitions,
    episode_returns,
    make_replay_buffer,
    split_by_episode,
)
from torchrl_wbrm.data.sampling import BufferBatches, PairedSampler
from torchrl_wbrm.data.lqr import LQRDataConfig, make_lqr_datasets
from torchrl_wbrm.data.minari_data import MinariDataConfig, make_minari_datasets, write_minari_dataset
from torchrl_wbrm.data.mountain_car import MountainCarDataConfig, make_mountain_car_datasets
from torchrl_wbrm.data.torchrl_minari import minari_replay_buffer

__all__ = [
    "OfflineDatasets",
    "BufferBatches",
    "PairedSampler",
    "collect_transitions",
    "episode_returns",
    "make_replay_buffer",
    "split_by_episode",
    "LQRDataConfig",
    "make_lqr_datasets",
    "MinariDataConfig",
    "make_minari_datasets",
    "write_minari_dataset",
    "minari_replay_buffer",
    "MountainCarDataConfig",
    "make_mountain_car_datasets",
]
