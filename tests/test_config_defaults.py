"""One source of truth for defaults: the recipe's YAML (``configs/wbrm_offline.yaml`` with its default groups)
composes to the schema's defaults, ``WBRMConfig()``, except the differences the YAML documents as by design."""
from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from torchrl_wbrm.configs import CONFIG_DIR
from torchrl_wbrm.training.config import WBRMConfig, register_configs

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


ENVS = sorted(p.stem for p in (CONFIG_DIR / "env").glob("*.yaml"))
#: what an env needs on the command line before it composes (the Minari datasets are mandatory, ``???``)
REQUIRED = {"minari": ["env.minari.expert=e", "env.minari.behaviour=b"]}


def test_every_env_group_is_covered():
    assert {"lqr_exp1", "mountain_car", "minari"} <= set(ENVS)


@pytest.mark.parametrize("env", ENVS)
def test_the_python_api_resolves_every_env_as_the_recipe_does(env):
    """``WBRMTrainer(WBRMConfig(env=...))`` and ``python recipes/wbrm_offline.py env=...`` run one method: the trainer
    resolves both through ``_to_config`` (the env's task fills what the config leaves null), and the results agree
    key by key, the env-specific ones (γ, the support term, the normalisation, the budget) included."""
    from hydra import compose, initialize_config_dir

    from torchrl_wbrm.data import EnvConfig
    from torchrl_wbrm.data.tasks import get_task
    from torchrl_wbrm.training.trainer import _to_config

    register_configs()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        composed = compose("wbrm_offline", overrides=[f"env={env}", *REQUIRED.get(env, [])])
    recipe = _to_config(composed)
    env_config = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(EnvConfig), composed.env))
    api = _to_config(WBRMConfig(env=env_config, threads=1))
    assert _flat(OmegaConf.to_container(OmegaConf.structured(api))) == \
        _flat(OmegaConf.to_container(OmegaConf.structured(recipe)))
    task = get_task(recipe.env)
    for key, value in task.training_defaults().items():  # every env-derived setting came from the task
        section, name = key.split(".")
        assert getattr(getattr(recipe, section), name) == value, key
