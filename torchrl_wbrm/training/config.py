"""Structured (dataclass) Hydra configs of the recipes: a misspelt key or a bad type fails at start.

``register_configs()`` stores the schemas in Hydra's ``ConfigStore``; the YAML files under ``configs/`` name
them first in their defaults list, so every value they set is checked against the schema.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from hydra.core.config_store import ConfigStore

from torchrl_wbrm.data import EnvConfig

__all__ = ["MakeDatasetConfig", "register_configs"]


@dataclass
class MakeDatasetConfig:
    """``recipes/make_dataset.py``: collect an offline dataset and save it.

    Attributes:
        env: the environment and its data settings (group ``env``).
        seed: the data seed.
        out: output directory (relative paths are relative to the launch directory).
        storage: ``"lazy"`` (RAM) or ``"memmap"`` (disk) replay-buffer storage while collecting.
    """

    env: EnvConfig = field(default_factory=EnvConfig)
    seed: int = 0
    out: str = "datasets/${env.name}_seed${seed}"
    storage: str = "lazy"


def register_configs() -> None:
    cs = ConfigStore.instance()
    cs.store(name="base_make_dataset", node=MakeDatasetConfig)
    cs.store(group="env", name="base_env", node=EnvConfig)
