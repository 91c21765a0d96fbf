"""The network options of the builders and of the recipe's config: activations by name, depth and widths, layer
normalisation, ensembles, value scaling, input normalisation and the learning-rate schedule."""
from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from torch import nn

from torchrl_wbrm.configs import CONFIG_DIR
from torchrl_wbrm.modules import (
    ACTIVATIONS,
    DensityRatioNetwork,
    EnsembleReduction,
    NormalisedMLP,
    make_deterministic_actor,
    make_discrete_q_network,
    make_q_network,
    make_tanh_normal_actor,
    resolve_activation,
)
from torchrl_wbrm.training import WBRMConfig, validate_config

from tests.inprocess import run_script

ROOT = Path(__file__).resolve().parents[1]


def _td(n=7, obs=3, act=2):
    return TensorDict({"observation": torch.randn(n, obs), "action": torch.randn(n, act)}, [n])


def _activations(module: nn.Module) -> set[type]:
    return {type(m) for m in module.modules() if type(m).__name__ in ACTIVATIONS}


@pytest.mark.parametrize("name, cls", [("SiLU", nn.SiLU), ("silu", nn.SiLU), ("ELU", nn.ELU), ("gelu", nn.GELU),
                                       ("Tanh", nn.Tanh), ("ReLU", nn.ReLU), (nn.Mish, nn.Mish)])
def test_resolve_activation_by_name_or_class(name, cls):
    assert resolve_activation(name) is cls


def test_unknown_activation_names_the_key():
    with pytest.raises(ValueError, match=r"q\.activation='Swoosh' is not a torch\.nn activation"):
        resolve_activation("Swoosh", key="q.activation")
    with pytest.raises(ValueError, match="not a torch.nn activation"):
        resolve_activation("Linear")  # a torch.nn module, not an activation


@pytest.mark.parametrize("key", ["q.activation", "q.actor_activation", "ratio.activation"])
def test_config_refuses_unknown_activation_naming_the_key(key):
    cfg = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(WBRMConfig), OmegaConf.from_dotlist([f"{key}=Nope"])))
    with pytest.raises(ValueError, match=key.replace(".", r"\.") + "='Nope'"):
        validate_config(cfg)


@pytest.mark.parametrize("override, match", [
    ("q.ensemble_size=0", "q.ensemble_size"), ("q.ensemble_reduction=max", "q.ensemble_reduction"),
    ("q.lr_schedule=linear", "q.lr_schedule"), ("q.value_scale=-1.0", "q.value_scale"),
    ("q.num_cells=[64,0]", "q.num_cells"),
])
def test_config_refuses_bad_network_settings(override, match):
    cfg = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(WBRMConfig), OmegaConf.from_dotlist([override])))
    with pytest.raises(ValueError, match=match.replace(".", r"\.")):
        validate_config(cfg)


def test_every_builder_takes_the_activation_depth_and_layer_norm():
    from torchrl.data import Bounded

    spec = Bounded(-1.0, 1.0, (2,))
    builders = [
        make_q_network(3, 2, initial_bias=0.0, num_cells=(8, 8, 8), activation="ELU", layer_norm=True),
        make_discrete_q_network(3, 4, num_cells=(8, 8, 8), activation="ELU", layer_norm=True),
        make_deterministic_actor(3, spec, num_cells=(8, 8, 8), activation="ELU", layer_norm=True),
        make_tanh_normal_actor(3, spec, num_cells=(8, 8, 8), activation="ELU", layer_norm=True),
        DensityRatioNetwork(3, 2, num_cells=(8, 8, 8), activation="ELU", layer_norm=True),
    ]
    for net in builders:
        linears = [m for m in net.modules() if isinstance(m, nn.Linear)]
        norms = [m for m in net.modules() if isinstance(m, nn.LayerNorm)]
        assert len(linears) == 4 and len(norms) == 3, net  # depth 3 + the output layer; a norm per hidden layer
        assert _activations(net) == {nn.ELU}, net


def test_q_network_starts_at_its_initial_bias_whatever_the_value_scale():
    torch.manual_seed(0)
    td = _td()
    for scale in (1.0, 10.0):
        q = make_q_network(3, 2, num_cells=(16,), initial_bias=100.0, value_scale=scale)
        with torch.no_grad():  # zero the last layer's weights: the output is the bias alone
            last = [m for m in q.modules() if isinstance(m, nn.Linear)][-1]
            last.weight.zero_()
        torch.testing.assert_close(q(td.clone())["state_action_value"], torch.full((7, 1), 100.0))


def test_value_scale_multiplies_the_network():
    torch.manual_seed(0)
    q1 = make_q_network(3, 2, initial_bias=0.0, num_cells=(16,), value_scale=1.0)
    torch.manual_seed(0)
    q10 = make_q_network(3, 2, initial_bias=0.0, num_cells=(16,), value_scale=10.0)
    td = _td()
    torch.testing.assert_close(q10(td.clone())["state_action_value"], 10 * q1(td.clone())["state_action_value"])


@pytest.mark.parametrize("reduction", ["mean", "min"])
def test_ensemble_reduces_independent_members(reduction):
    torch.manual_seed(0)
    q = make_q_network(3, 2, initial_bias=0.0, num_cells=(16,), num_members=2, ensemble_reduction=reduction)
    ensemble = next(m for m in q.modules() if isinstance(m, EnsembleReduction))
    a, b = ensemble.members
    assert not torch.equal(a[0].weight, b[0].weight)  # independently initialised
    td = _td()
    x = torch.cat([td["observation"], td["action"]], -1)
    expected = (a(x) + b(x)) / 2 if reduction == "mean" else torch.minimum(a(x), b(x))
    torch.testing.assert_close(q(td)["state_action_value"], expected)


def test_observation_normalisation_is_a_fixed_input_layer():
    torch.manual_seed(0)
    loc, scale = torch.tensor([1.0, -2.0, 3.0]), torch.tensor([2.0, 0.5, 4.0])
    q = make_q_network(3, 2, initial_bias=0.0, num_cells=(16,), observation_loc=loc, observation_scale=scale)
    normalised = next(m for m in q.modules() if isinstance(m, NormalisedMLP))
    td = _td()
    expected = normalised.net(torch.cat([(td["observation"] - loc) / scale, td["action"]], -1))  # action unchanged
    torch.testing.assert_close(q(td)["state_action_value"], expected)
    assert {"module.loc", "module.scale"} <= set(q.state_dict())  # saved with the model, not trained
    assert not any(p is normalised.loc or p is normalised.scale for p in q.parameters())
    with pytest.raises(ValueError, match="observation_scale"):
        make_q_network(3, 2, initial_bias=0.0, observation_loc=loc, observation_scale=torch.tensor([1.0, 0.0, 1.0]))
    with pytest.raises(ValueError, match="both"):
        make_q_network(3, 2, initial_bias=0.0, observation_loc=loc)


def _trainer(tmp_path, *overrides, resume=False):
    from hydra import compose, initialize_config_dir

    from torchrl_wbrm.training import WBRMTrainer, register_configs

    register_configs()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("wbrm_offline", overrides=[
            "env.lqr_data.behaviour_episodes=60", "env.lqr_data.expert_episodes=30", "env.lqr_data.parallel_envs=30",
            "ratio.steps=10", "ratio.eval_every=5", "q.num_cells=[16,16]", "q.actor_num_cells=[16,16]",
            "eval.offline_value=false", "eval.episodes=50", "eval.train_episodes=20", "eval.q_samples=200", "logger=none", "plots=false",
            *overrides])
    return WBRMTrainer(cfg, tmp_path, progress=False, resume=resume)


def test_recipe_defaults_smooth_q_and_the_options_reach_the_networks(tmp_path, single_thread):
    default = _trainer(tmp_path / "default", "q.steps=4")
    assert _activations(default.q_loss.value_network) == {nn.GELU}  # the recipe's Q is smooth
    assert _activations(default.actor) == {nn.ReLU}
    assert _activations(default.ratio_network) == {nn.ReLU}
    t = _trainer(tmp_path / "options", "q.steps=4", "q.activation=SiLU", "q.actor_activation=Tanh",
                 "ratio.activation=ELU", "q.layer_norm=true", "q.ensemble_size=2", "q.normalise_observations=true")
    assert _activations(t.q_loss.value_network) == {nn.SiLU}
    assert _activations(t.actor) == {nn.Tanh}
    assert _activations(t.ratio_network) == {nn.ELU}
    assert any(isinstance(m, nn.LayerNorm) for m in t.q_loss.value_network.modules())
    assert any(isinstance(m, EnsembleReduction) for m in t.q_loss.value_network.modules())
    normalised = next(m for m in t.actor.modules() if isinstance(m, NormalisedMLP))
    observations = t.q_train_data["observation"]
    torch.testing.assert_close(normalised.loc[:2], observations.mean(0), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(normalised.scale[:2], observations.std(0), rtol=1e-4, atol=1e-5)


def test_cosine_schedule_anneals_every_optimiser_and_resumes_exactly(tmp_path, single_thread):
    lr = WBRMConfig().q.lr
    t = _trainer(tmp_path / "full", "q.steps=6", "q.eval_every=6", "q.lr_schedule=cosine", "checkpoint_every=3")
    t.run()
    for name, optimiser in t.optimisers.items():  # at the end of the budget the cosine reaches 0
        assert optimiser.param_groups[0]["lr"] == pytest.approx(0.0, abs=1e-12), name
    half = _trainer(tmp_path / "half", "q.steps=6", "q.eval_every=6", "q.lr_schedule=cosine", "checkpoint_every=3")
    half.run(until=3)
    for optimiser in half.optimisers.values():
        assert optimiser.param_groups[0]["lr"] == pytest.approx(lr * 0.5 * (1 + math.cos(math.pi * 3 / 6)))
    resumed = _trainer(tmp_path / "half", "q.steps=6", "q.eval_every=6", "q.lr_schedule=cosine", resume=True)
    resumed_results = resumed.run()
    full = t.q_loss.state_dict()
    for key, value in resumed.q_loss.state_dict().items():
        torch.testing.assert_close(value, full[key], rtol=0, atol=0, msg=key)
    assert resumed_results["final"]["regret"] == t.history[-1]["regret"]


def test_q_accuracy_study_quick(tmp_path):
    out = tmp_path / "study"
    proc = run_script(ROOT / "recipes" / "q_accuracy_study.py", "--quick", "--jobs", "1", "--out", out)
    assert proc.returncode == 0, proc.stderr[-3000:]
    tables = (out / "tables.md").read_text()
    assert "### activation" in tables and "| lqr_exp1 | ReLU |" in tables and "SiLU (default)" in tables
    assert "### Selection (no ground truth)" in tables
    assert (out / "q_accuracy_study.png").stat().st_size > 0
    # --report-only rebuilds both from the finished runs and trains nothing
    runs = sorted(p.stat().st_mtime_ns for p in out.rglob("results.json"))
    (out / "tables.md").unlink(), (out / "q_accuracy_study.png").unlink()
    proc = run_script(ROOT / "recipes" / "q_accuracy_study.py", "--quick", "--report-only", "--out", out)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (out / "tables.md").read_text() == tables and (out / "q_accuracy_study.png").stat().st_size > 0
    assert sorted(p.stat().st_mtime_ns for p in out.rglob("results.json")) == runs


def _compose(*overrides):
    from hydra import compose, initialize_config_dir

    from torchrl_wbrm.training import register_configs

    register_configs()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose("wbrm_offline", overrides=list(overrides))


def test_env_defaults_apply_to_their_env_only_and_the_command_line_wins():
    """The env's settings come from its task object (its typed Task.TRAINING_DEFAULTS), not from YAML: the recipe's composed
    config leaves them null and resolve_defaults fills them, so the Python API gets the same values."""
    from torchrl_wbrm.tasks import LQRTask, MinariTask, MountainCarTask
    from torchrl_wbrm.training import WBRMConfig, resolve_defaults
    from torchrl_wbrm.training.config import to_config

    mc = _compose("env=mountain_car")
    assert mc.q.bc_alpha is None and mc.q.steps is None and mc.q.gamma is None  # nothing env-specific in YAML
    resolved = to_config(mc)
    for section, name, value in MountainCarTask.TRAINING_DEFAULTS.items():
        if value is not None:  # gamma: the task's default_gamma
            assert getattr(getattr(resolved, section), name) == value, (section, name)
    assert resolved.q.gamma == MountainCarTask.default_gamma == 0.9999
    assert resolved.q.bc_alpha == 10.0 and resolved.q.expert_bc_alpha == 0 and resolved.q.normalise_observations
    # the Python API, from the schema alone, resolves to the same config as the recipe
    api = resolve_defaults(WBRMConfig(env=to_config(mc).env, threads=1))  # threads: the recipe's one difference
    assert api == resolved
    lqr = to_config(_compose("env=lqr_exp1"))
    assert lqr.q.expert_bc_alpha == LQRTask.TRAINING_DEFAULTS.q.expert_bc_alpha == 1.0
    assert not lqr.q.normalise_observations and lqr.q.gamma == 0.9 and lqr.eval.episodes == 1000
    assert MinariTask.TRAINING_DEFAULTS.q.expert_bc_alpha == 1.0  # the shared default, not MountainCar's
    assert to_config(_compose("env=mountain_car", "q.bc_alpha=1.0")).q.bc_alpha == 1.0  # the command line wins
    assert to_config(_compose("env=mountain_car", "q.steps=7")).q.steps == 7
    # one support term: choosing one leaves the other off; both on is refused by name
    chosen = to_config(_compose("env=lqr_exp1", "q.bc_alpha=2.5")).q
    assert (chosen.bc_alpha, chosen.expert_bc_alpha) == (2.5, 0.0)
    chosen = to_config(_compose("env=mountain_car", "q.expert_bc_alpha=1.0")).q
    assert (chosen.bc_alpha, chosen.expert_bc_alpha) == (0.0, 1.0)
    from torchrl_wbrm.training.config import validate_config

    with pytest.raises(ValueError, match="q.bc_alpha=2.5 .* q.expert_bc_alpha=1.5"):
        validate_config(to_config(_compose("env=lqr_exp1", "q.bc_alpha=2.5", "q.expert_bc_alpha=1.5")))
    assert to_config(_compose("env=mountain_car", "algo=td3bc")).q.gamma == 0.9999  # baselines get them too
