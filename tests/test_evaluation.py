"""Evaluation: confidence intervals, paired regret against the exact optimum, Q* and ratio errors."""
from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from torchrl_wbrm.envs import LQREnv
from torchrl_wbrm.evaluation import (
    FiniteHorizonLQRPolicy,
    bootstrap_ci,
    discounted_returns,
    evaluate_returns,
    lqr_paired_regret,
    mean_ci,
    q_error,
    ratio_error,
)
from torchrl_wbrm.policies import LinearGaussianPolicy, make_lqr_optimal_policy, make_mountain_car_env, make_mountain_car_expert


def test_mean_ci_known_answer():
    ci = mean_ci([1.0, 2.0, 3.0, 4.0, 5.0])
    assert ci.mean == 3.0 and ci.n == 5
    se = math.sqrt(2.5 / 5)
    assert ci.stderr == pytest.approx(se)
    assert ci.high - 3.0 == pytest.approx(2.7764451 * se, rel=1e-6)  # t_{0.975, 4}
    assert math.isnan(mean_ci([1.0]).stderr)
    with pytest.raises(ValueError, match="empty"):
        mean_ci([])


def test_bootstrap_is_seeded_and_covers_the_mean():
    x = torch.randn(200, generator=torch.Generator().manual_seed(0))
    a, b = bootstrap_ci(x, seed=1), bootstrap_ci(x, seed=1)
    assert (a.low, a.high) == (b.low, b.high)
    assert a.low < x.mean().item() < a.high
    assert a.half_width == pytest.approx(1.96 * x.std().item() / math.sqrt(200), rel=0.2)


@pytest.mark.parametrize("experiment", ["exp1", "exp3"])
def test_paired_regret_of_known_policies(experiment):
    env = LQREnv(experiment)
    optimal = TensorDictModule(FiniteHorizonLQRPolicy(env), in_keys=["observation", "step_count"], out_keys=["action"])
    res = lqr_paired_regret(experiment, optimal, episodes=2000, seed=0)
    assert res["regret"].mean == 0.0  # the same policy on the same noise
    assert res["optimal_return_paired"].low < res["optimal_return_exact"] < res["optimal_return_paired"].high
    stationary = lqr_paired_regret(experiment, make_lqr_optimal_policy(env), episodes=2000, seed=0)
    _, K = env.riccati()
    exact_gap = env.optimal_return(clipped=False) - env.policy_return(K, clipped=False)
    assert abs(stationary["regret"].mean - exact_gap) < 4 * stationary["regret"].stderr + 1e-5
    assert stationary["regret"].stderr < 1e-4  # pairing: the regret is far sharper than either return
    assert stationary["return"].stderr > 100 * stationary["regret"].stderr
    _, K = env.riccati()
    worse = TensorDictModule(LinearGaussianPolicy(0.7 * K, 0.0), in_keys=["observation"], out_keys=["action"])
    res = lqr_paired_regret(experiment, worse, episodes=2000, seed=0)
    exact_gap = env.optimal_return(clipped=False) - env.policy_return(0.7 * K, clipped=False)
    assert res["regret"].low - 0.01 < exact_gap < res["regret"].high + 0.01 and exact_gap > 0.01


def test_q_error_scores():
    env = LQREnv("exp1")
    x = torch.randn(1000, 2, dtype=torch.float64)
    a = env.optimal_action(x) + 0.1 * torch.randn(1000, 2, dtype=torch.float64)
    q = env.optimal_q(x, a)
    assert q_error(q, q)["relative_spread_error"] == 0.0
    constant = q_error(torch.full_like(q, q.mean().item()), q)
    assert constant["relative_spread_error"] == pytest.approx(1.0, rel=0.01)  # a constant Q explains nothing
    shifted = q_error(q + 2.0, q)
    assert shifted["bias"] == pytest.approx(2.0) and shifted["centred_error"] == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(ValueError, match="values"):
        q_error(q[:10], q)


def test_ratio_error_and_ess():
    from torchrl_wbrm.objectives.functional import effective_sample_size  # Kish's, the one definition

    w = torch.tensor([1.0, 1.0, 1.0, 1.0])
    assert effective_sample_size(w) == 4.0
    assert effective_sample_size(torch.tensor([4.0, 0.0, 0.0, 0.0])) == 1.0
    out = ratio_error(torch.tensor([2.0, 0.0]), torch.tensor([1.0, 1.0]))
    assert out["relative_l2"] == pytest.approx(1.0) and out["mean_behaviour"] == 1.0 and out["ess_fraction"] == 0.5


def test_evaluate_returns_on_mountain_car():
    env = make_mountain_car_env()
    res = evaluate_returns(env, make_mountain_car_expert(power=0.3, tau=0.0), episodes=2, seed=0)
    assert res.mean > 95 and res.n == 2


def test_discounted_returns_stop_at_each_episodes_done():
    reward = torch.tensor([[1.0, 2.0, 4.0, 8.0], [1.0, 1.0, 1.0, 1.0]]).unsqueeze(-1)
    done = torch.tensor([[False, True, True, True], [False, False, False, True]]).unsqueeze(-1)
    rollout = TensorDict({"next": {"reward": reward, "done": done}}, batch_size=[2, 4])
    expected = torch.tensor([1 + 1.0, 1 + 0.5 + 0.25 + 0.125], dtype=torch.float64)  # nothing after the first done
    torch.testing.assert_close(discounted_returns(rollout, 0.5), expected)
    no_done = TensorDict({"next": {"reward": reward}}, batch_size=[2, 4])
    assert discounted_returns(no_done, 1.0).tolist() == [15.0, 4.0]


def test_evaluate_returns_on_batched_mountain_car_counts_each_episode_once():
    """Cars finish at different steps; a finished car's repeated last transition (+100) must not count again."""
    episodes = 20
    policy = make_mountain_car_expert(power=0.3, tau=0.0)
    res = evaluate_returns(make_mountain_car_env(batch_size=[episodes]), policy, episodes=episodes, seed=0)
    assert res.n == episodes and 97 < res.mean < 100  # each return is 100 - 0.009 * length
    one_by_one = evaluate_returns(make_mountain_car_env(), policy, episodes=3, seed=0)
    assert abs(res.mean - one_by_one.mean) < 0.5


def test_a_policy_on_another_device_than_the_env_gets_torchrls_cast():
    """A policy trained on an accelerator (here on torch's ``meta`` device) acting in an env that steps on the CPU
    gets ``auto_cast_to_device``; a policy on the env's device, or one without parameters, takes the plain rollout
    (the LQR env's shortcut among them). The rollout itself on CUDA: ``tests/test_fast_gpu.py``."""
    from torch import nn

    from torchrl_wbrm.evaluation.metrics import _cast_to

    policy = TensorDictModule(nn.Linear(2, 2), in_keys=["observation"], out_keys=["action"])
    assert _cast_to(policy, torch.device("cpu")) == {} and _cast_to(policy, "cpu") == {}
    assert _cast_to(lambda td: td, "cpu") == {}
    assert _cast_to(policy.to("meta"), torch.device("cpu")) == {"auto_cast_to_device": True}
    assert _cast_to(policy, None) == {}
