"""The recipes' Hydra configs: ``wbrm_offline.yaml``, ``make_dataset.yaml`` and the ``env/`` and ``logger/`` groups
(the ``algo`` group's nodes are the registry's, stored by :func:`~torchrl_wbrm.training.config.register_configs`).

They live in the clone's top-level ``configs/``, which the build maps into the package as ``torchrl_wbrm.configs``
(``setup.py``), so a wheel ships them and an editable install finds them alike. :data:`CONFIG_DIR` is their
directory; compose a recipe's config with Hydra's compose API
(``hydra.initialize_config_dir(config_dir=str(CONFIG_DIR))``)::

    >>> from torchrl_wbrm.configs import CONFIG_DIR
    >>> (CONFIG_DIR / "wbrm_offline.yaml").is_file()
    True
"""
from __future__ import annotations

from pathlib import Path

__all__ = ["CONFIG_DIR"]

#: The directory of the recipes' YAML configs (a clone's ``configs/``; an installed wheel's ``torchrl_wbrm/configs``).
CONFIG_DIR = Path(__file__).resolve().parent
