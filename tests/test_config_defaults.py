"""One source of truth for defaults: the recipe's YAML (``torchrl_wbrm/configs/wbrm_offline.yaml`` with its default groups)
composes to the schema's defaults, ``WBRMConfig()``, except the differences the YAML documents as by design."""
from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from torchrl_wbrm.training.config import WBRMConfig, register_configs

CONFIG_DIR = Path(__file__).resolve().parents[1] / "torchrl_wbrm" / "configs"

#: set by the YAML on purpose (its comments say why): none of them changes the method
INTENDED = {"threads": 1}


def _flat(tree, prefix=""):
    if isinstance(tree, dict):
        out = {}
        for key, value in tree.items():
            out.update(_flat(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: tree}


def test_the_recipe_yaml_composes_to_the_schema_defaults():
    from hydra import compose, initialize_config_dir

    register_configs()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        composed = compose("wbrm_offline")
    recipe = _flat(OmegaConf.to_container(OmegaConf.structured(OmegaConf.to_object(composed))))
    schema = _flat(OmegaConf.to_container(OmegaConf.structured(WBRMConfig())))
    assert recipe.keys() == schema.keys()
    differences = {key: (schema[key], recipe[key]) for key in schema if schema[key] != recipe[key]}
    assert differences == {key: (schema[key], value) for key, value in INTENDED.items()}, differences


def test_the_yaml_sets_only_its_by_design_values():
    """Every value the top-level YAML sets (outside its defaults list and Hydra's own section) is listed above."""
    top = OmegaConf.to_container(OmegaConf.load(CONFIG_DIR / "wbrm_offline.yaml"))
    top.pop("defaults"), top.pop("hydra")
    assert _flat(top) == INTENDED
