"""One source of truth for defaults: the recipe's YAML (``configs/wbrm_offline.yaml`` with its default groups)
composes to the schema's defaults, ``WBRMConfig()``, key by key, ``threads`` included; ``WBRMConfig(env="<name>")``
selects an env config as ``env=<name>`` does on the recipe's command line; ``WBRMTrainer(cfg)`` picks a run directory
named as the recipe's."""
from __future__ import annotations

import inspect
import re

import pytest
from omegaconf import OmegaConf

from torchrl_wbrm.configs import CONFIG_DIR
from torchrl_wbrm.training.config import WBRMConfig, register_configs


def _flat(tree, prefix=""):
    if isinstance(tree, dict):
        out = {}
        for key, value in tree.items():
            out.update(_flat(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: tree}


def _as_flat(cfg) -> dict:
    return _flat(OmegaConf.to_container(OmegaConf.structured(cfg)))


def _compose(*overrides: str):
    from hydra import compose, initialize_config_dir

    register_configs()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose("wbrm_offline", overrides=list(overrides))


def test_the_recipe_yaml_composes_to_the_schema_defaults():
    """Every key of ``WBRMConfig()`` equals the recipe's composed default, with no exception (``threads`` is 1 in
    both: one torch thread per run)."""
    recipe = _as_flat(OmegaConf.to_object(_compose()))
    schema = _as_flat(WBRMConfig())
    assert recipe.keys() == schema.keys()
    assert {key: (schema[key], recipe[key]) for key in schema if schema[key] != recipe[key]} == {}
    assert schema["threads"] == 1


def test_the_yaml_sets_nothing_the_schema_does_not():
    """A value the top-level YAML sets (outside its defaults list and Hydra's own section) equals the schema's."""
    top = OmegaConf.to_container(OmegaConf.load(CONFIG_DIR / "wbrm_offline.yaml"))
    top.pop("defaults"), top.pop("hydra")
    schema = _as_flat(WBRMConfig())
    assert {key: value for key, value in _flat(top).items() if schema.get(key, object()) != value} == {}


ENVS = sorted(p.stem for p in (CONFIG_DIR / "env").glob("*.yaml"))


def _required(env: str) -> dict:
    """What an env needs on the command line before it composes: for ``minari`` its two datasets (mandatory,
    ``???``), a real pair, since its defaults depend on the datasets' action space."""
    if env != "minari":
        return {}
    from minari_helpers import mountain_car_datasets

    data = mountain_car_datasets()
    return {"env.minari.expert": data["expert_path"], "env.minari.behaviour": data["behaviour_path"]}


def test_every_env_group_is_covered():
    assert {"lqr_exp1", "mountain_car", "minari"} <= set(ENVS)


@pytest.mark.parametrize("env", ENVS)
def test_an_env_named_by_string_is_the_recipes_env(env):
    """``WBRMConfig(env="<name>")`` equals ``python recipes/wbrm_offline.py env=<name>`` for every key, before and
    after the env's task fills what the config leaves null (γ, the support term, the budget, ...)."""
    from torchrl_wbrm.tasks import get_task
    from torchrl_wbrm.training.config import to_config

    required = _required(env)
    composed = _compose(f"env={env}", *(f"{k}={v}" for k, v in required.items()))
    api = WBRMConfig(env=env)
    for key, value in required.items():  # the Minari pair: set on the config, as a user does
        assert OmegaConf.select(OmegaConf.structured(api), key) == ""
        setattr(api.env.minari, key.rsplit(".", 1)[1], value)
    assert _as_flat(api) == _as_flat(OmegaConf.to_object(composed))
    recipe = to_config(composed)
    assert _as_flat(to_config(api)) == _as_flat(recipe)
    task = get_task(recipe.env)
    for section, name, value in task.training_defaults().items():  # every env-derived setting came from the task
        assert getattr(getattr(recipe, section), name) == value, (section, name)


def test_an_unknown_env_name_is_refused_naming_the_choices():
    with pytest.raises(ValueError, match=r"env='lqr_exp9' is not an env config; the env configs are: .*lqr_exp1"):
        WBRMConfig(env="lqr_exp9")


def test_the_default_run_directory_is_named_as_the_recipes(tmp_path):
    """``WBRMTrainer(cfg)`` needs no run directory: ``default_run_dir`` gives the recipe's
    ``outputs/wbrm_offline/<env.name>/<date>_seed<seed>``, a fresh one for each call (``_1``, ``_2``, ...)."""
    from torchrl_wbrm.training.trainer import WBRMTrainer, default_run_dir

    assert inspect.signature(WBRMTrainer).parameters["run_dir"].default is None
    cfg = WBRMConfig(env="lqr_exp2", seed=3)
    first, second = default_run_dir(cfg, tmp_path / "outputs"), default_run_dir(cfg, tmp_path / "outputs")
    assert first.parent == second.parent == tmp_path / "outputs" / "lqr_exp2"
    assert re.fullmatch(r"\d{4}-\d\d-\d\d_\d\d-\d\d-\d\d_seed3", first.name), first.name
    assert first != second and first.is_dir() and second.is_dir()
    recipe_dir = OmegaConf.to_container(OmegaConf.load(CONFIG_DIR / "wbrm_offline.yaml"))["hydra"]["run"]["dir"]
    assert recipe_dir == "outputs/wbrm_offline/${env.name}/${now:%Y-%m-%d_%H-%M-%S}_seed${seed}"


def test_a_resume_needs_its_run_directory(tmp_path, monkeypatch):
    from torchrl_wbrm.training.trainer import WBRMTrainer

    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError, match="resume=True needs the run directory"):
        WBRMTrainer(WBRMConfig(), resume=True)
    assert not (tmp_path / "outputs").exists()
