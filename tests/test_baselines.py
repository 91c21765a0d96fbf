"""Baselines as configurations of the shared trainer (``algo=...``, :mod:`torchrl_wbrm.training.algos`).

Each algo runs through :class:`~torchrl_wbrm.training.WBRMTrainer` on a tiny budget and writes its results; then each
learns LQR exp1 to a checked answer on a modest budget (D = 1,000 behaviour episodes = 18,000 transitions after the
held-out split, 64-unit networks, batch 256, Adam). Reference points on exp1 (paired regret, 1,000 episodes): the
behaviour policy ≈ 2.3 (its action noise), the zero-action policy 0.357 ± 0.023, the optimum 0. The thresholds sit
between what each algo measured (seed 0, one thread; in the test's comments) and the zero-action policy.
"""
from __future__ import annotations

import json

import pytest
import torch
from tensordict import TensorDict

from torchrl_wbrm.envs import LQRConfig, make_lqr_env
from torchrl_wbrm.training import WBRMTrainer
from torchrl_wbrm.training.algos import ALGOS, ActionGrid
from torchrl_wbrm.training.config import WBRMConfig, validate_config

from tests.test_training import tiny_config

ZERO_ACTION_REGRET = 0.357  # paired regret of a ≡ 0 on exp1 (1,000 episodes, eval seed), ± 0.023


@pytest.mark.parametrize("algo", sorted(ALGOS))
def test_each_algo_runs_through_the_trainer(tmp_path, single_thread, algo):
    trainer = WBRMTrainer(tiny_config(algo=algo, q={"steps": 20, "eval_every": 10}), tmp_path, progress=False)
    results = trainer.run()
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved["algo"] == results["algo"] == algo
    final = saved["final"]
    assert final["regret"] == final["regret"] and final["return"] == final["return"]  # present, not NaN
    has_q = algo != "bc"
    assert ("q_error_expert" in final) == has_q
    assert (trainer.ratio_network is not None) == (algo == "wbrm")
    assert ("held_out_bellman_residual" in final) == (algo in ("wbrm", "brm", "fqi", "mabo"))
    assert saved["ratio"]["source"] == ("learned" if algo == "wbrm" else "none")
    if algo not in ("wbrm", "bc"):  # baselines never see the stage-1 weights
        assert (trainer.q_buffer[:]["density_ratio"] == 1).all()


def test_algo_choice_is_validated():
    from omegaconf import OmegaConf

    cfg = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(WBRMConfig), {"algo": "sac"}))
    with pytest.raises(ValueError, match="algo='sac'"):
        validate_config(cfg)
    cfg = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(WBRMConfig), {"baselines": {"iql": {"expectile": 1.0}}}))
    with pytest.raises(ValueError, match="expectile"):
        validate_config(cfg)


def test_action_grid_is_the_env_discretizer_and_round_trips():
    grid = ActionGrid.from_lqr_env(LQRConfig(), 5)  # bound 5: bin medians -4, -2, 0, 2, 4
    torch.testing.assert_close(grid.values, torch.tensor([[-4.0, -2.0, 0.0, 2.0, 4.0]] * 2))
    index = torch.arange(grid.num_actions)
    assert grid.num_actions == 25
    torch.testing.assert_close(grid.index(grid(index)), index)
    # nearest grid point per coordinate, coordinate 0 most significant: (0.3, -4.2) -> (0, -4) -> 2 * 5 + 0
    assert grid.index(torch.tensor([[0.3, -4.2]])).item() == 10
    # the env's ActionDiscretizer maps the per-coordinate indices (2, 0) to the same action
    env = make_lqr_env("exp1", discretize_actions=5, seed=0)
    td = env.reset().set("action", torch.tensor([2, 0]))
    continuous = env.transform.inv(td.clone())["action"]
    torch.testing.assert_close(continuous, grid(torch.tensor(10)))


def _learning_config(algo: str, steps: int, **overrides) -> WBRMConfig:
    base = {
        "env": {"lqr_data": {"behaviour_episodes": 2000, "expert_episodes": 100, "parallel_envs": 500}},
        "ratio": {"source": "none"},
        "q": {"steps": steps, "eval_every": steps, "batch_size": 256, "lr": 3e-3, "actor_lr": 3e-3,
              "num_cells": [64, 64], "actor_num_cells": [64, 64]},
        "eval": {"episodes": 1000, "train_episodes": 100, "q_samples": 2000},
        "checkpoint_every": 0,
    }
    for key, value in overrides.items():
        base[key] = {**base.get(key, {}), **value} if isinstance(value, dict) else value
    return tiny_config(algo=algo, **base)


# (algo, steps, overrides, regret threshold); measured regret at seed 0 in the comment
LEARNING = [
    ("brm", 1000, {}, 0.2),  # unweighted BRM: 0.056 ± 0.008 (seed 1: 0.035), 5 s
    ("fqi", 1000, {}, 0.2),  # K = 50: 0.127 ± 0.012 (seed 1: 0.047), 5 s
    ("td3bc", 1000, {}, 0.2),  # 0.109 ± 0.008 (seed 1: 0.104), 7 s
    ("ddpg", 1000, {}, 0.2),  # 0.064 ± 0.008 (seed 1: 0.061), 6 s
    ("iql", 1000, {}, 0.2),  # 0.055 ± 0.008 (seed 1: 0.047), 10 s
    ("cql", 300, {"baselines": {"cql": {"num_random": 4}}}, 0.3),  # 0.211 ± 0.007 (seed 1: 0.059), 9 s (slow per step)
]


@pytest.mark.slow
@pytest.mark.parametrize("algo, steps, overrides, threshold", LEARNING, ids=[row[0] for row in LEARNING])
def test_each_baseline_learns_lqr(tmp_path, single_thread, algo, steps, overrides, threshold):
    results = WBRMTrainer(_learning_config(algo, steps, **overrides), tmp_path, progress=False).run()
    final = results["final"]
    assert final["regret"] < threshold < ZERO_ACTION_REGRET, final["regret"]
    assert final["regret_ci"] < 0.05  # the paired estimate is sharp enough for the threshold to mean something


@pytest.mark.slow
def test_dqn_learns_q_on_a_covered_grid(tmp_path, single_thread):
    """Offline DQN learns Q̂ but its greedy policy is poor: Q̂ at grid actions the data rarely visit is overestimated.

    Grid: action box [−1.5, 1.5]² (``env.lqr.action_bound``; the dynamics ignore it, the behaviour data lie inside
    it), 5 bins per coordinate, 25 joint actions. Measured (seed 0, 1,500 steps, 5 s): Q̂ error / spread of Q* 0.66
    (a constant Q scores 1), paired regret 4.4 (seed 1: Q̂ error 0.67, regret 0.52; 3,000 steps, 7 bins: 1.4).
    """
    cfg = _learning_config("dqn", 1500, q={"lr": 1e-3}, baselines={"dqn": {"num_bins": 5}},
                           env={"lqr": {"action_bound": 1.5}})
    final = WBRMTrainer(cfg, tmp_path, progress=False).run()["final"]
    assert final["q_error_expert"] < 0.8, final["q_error_expert"]
    assert final["regret"] == final["regret"]
