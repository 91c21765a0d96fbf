"""The offline value estimate (FQE on D, no environment) against exact answers: a linear policy on LQR against the
closed-form return, a one-state problem by hand; and the closed-form value of a linear policy itself."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn

from torchrl_wbrm.data.lqr import LQRDataConfig, make_lqr_datasets
from torchrl_wbrm.envs import LQREnv
from torchrl_wbrm.evaluation.lqr_policy_value import linear_policy_q, linear_policy_value
from torchrl_wbrm.ope.offline_value import (
    TIME_LEFT_KEY,
    estimate_offline_value,
    initial_rows,
    with_time_left,
)
from torchrl_wbrm.policies.lqr import LinearGaussianPolicy


def _linear_policy(gain) -> TensorDictModule:
    return TensorDictModule(LinearGaussianPolicy(gain, 0.0), in_keys=["observation"], out_keys=["action"])


@pytest.mark.parametrize("experiment", ["exp1", "exp3"])
@pytest.mark.parametrize("noise", [0.0, 0.3])
def test_linear_policy_value_matches_long_horizon_return_and_optimum(experiment, noise):
    env = LQREnv(experiment)
    _, K = env.riccati()
    M = 0.7 * K
    P, v0 = linear_policy_value(env, M, noise)
    exact = v0 - float(torch.trace(torch.as_tensor(P)))  # E[V(x_0)], x_0 ~ N(0, I)
    assert exact == pytest.approx(env.policy_return(M, noise, horizon=400, clipped=False), abs=1e-6)
    x, a = torch.randn(50, 2, dtype=torch.float64), torch.randn(50, 2, dtype=torch.float64)
    torch.testing.assert_close(linear_policy_q(env, K, 0.0, x, a), env.optimal_q(x, a))


def test_linear_policy_value_refuses_unstable_gain():
    env = LQREnv("exp1")
    with pytest.raises(ValueError, match="infinite"):
        linear_policy_value(env, -10 * torch.eye(2), 0.0)


def _one_state_episodes(episodes: int, horizon: int) -> TensorDict:
    """One state (x = 0), any action, reward 1 at every step, episodes of ``horizon`` steps."""
    n = episodes * horizon
    step = torch.arange(horizon).repeat(episodes)
    done = (step == horizon - 1).unsqueeze(-1)
    return TensorDict({
        "observation": torch.zeros(n, 1), "action": torch.randn(n, 1, generator=torch.Generator().manual_seed(0)),
        "step_count": step.unsqueeze(-1), "episode": torch.arange(episodes).repeat_interleave(horizon),
        ("next", "observation"): torch.zeros(n, 1), ("next", "reward"): torch.ones(n, 1),
        ("next", "done"): done, ("next", "terminated"): torch.zeros(n, 1, dtype=torch.bool),
        ("next", "step_count"): (step + 1).unsqueeze(-1),
    }, [n])


def test_time_left_and_initial_rows():
    data = _one_state_episodes(3, 4)
    prepared = with_time_left(data, 4)
    torch.testing.assert_close(prepared[TIME_LEFT_KEY][:4].squeeze(-1), torch.tensor([1.0, 0.75, 0.5, 0.25]))
    torch.testing.assert_close(prepared["next", TIME_LEFT_KEY][:4].squeeze(-1), torch.tensor([0.75, 0.5, 0.25, 0.0]))
    assert prepared["next", "terminated"].equal(data["next", "done"])
    assert not data["next", "terminated"].any()  # the input is not modified
    assert initial_rows(data).tolist() == [0, 4, 8]
    assert initial_rows(data.exclude("step_count")).tolist() == [0, 4, 8]
    with pytest.raises(ValueError, match="past horizon=3"):
        with_time_left(data, 3)


def test_one_state_problem_by_hand(single_thread):
    """Reward 1 for 5 steps at γ = ½: the finite-horizon return is Σ_{t<5} ½^t = 1.9375; the infinite-horizon value
    1 / (1 − ½) = 2. The policy is irrelevant (one state); the estimate is exact to the fit's precision."""
    data = _one_state_episodes(20, 5)
    policy = TensorDictModule(nn.Linear(1, 1), in_keys=["observation"], out_keys=["action"])
    finite = estimate_offline_value(policy, data, gamma=0.5, horizon=5, steps=1000, num_cells=(16,), lr=3e-3)
    assert finite.value == pytest.approx(1.9375, abs=0.015)
    assert finite.episodes == 20 and not finite.uses_environment and "at most 5 steps" in finite.quantity
    infinite = estimate_offline_value(policy, data, gamma=0.5, horizon=None, steps=1000, num_cells=(16,), lr=3e-3)
    assert infinite.value == pytest.approx(2.0, abs=0.015)
    with pytest.raises(ValueError, match="below 1 without a horizon"):
        estimate_offline_value(policy, data, gamma=1.0, horizon=None)


@pytest.mark.slow
def test_linear_policy_on_lqr_within_tolerance_of_closed_form(single_thread):
    """FQE of the deterministic expert gain (0.95 K) on behaviour data (a = −0.5 K x + N(0, 0.5²), 250 episodes) vs
    the exact 20-step discounted return (``LQREnv.policy_return``, clipped reward, x_0 ∼ N(0, I)): within 0.3 (0.35%;
    measured 0.05). The naive figure, D's own mean return, is 2.3 below: the estimate has to evaluate the other
    policy, not the data."""
    env = LQREnv("exp1")
    _, K = env.riccati()
    data = make_lqr_datasets("exp1", LQRDataConfig(behaviour_episodes=500, expert_episodes=2), seed=0).transitions[:]
    gain = 0.95 * K
    truth = env.policy_return(gain, 0.0)
    estimate = estimate_offline_value(_linear_policy(gain), data, gamma=0.9, horizon=20, steps=2000, seed=0)
    assert abs(estimate.value - truth) < 0.3
    assert estimate.low < estimate.value < estimate.high and estimate.high - estimate.low < 1.0
    naive = torch.stack([data["next", "reward"].squeeze(-1)[data["episode"] == e] for e in data["episode"].unique()])
    naive = (naive.double() * 0.9 ** torch.arange(20, dtype=torch.float64)).sum(-1).mean().item()
    assert abs(naive - truth) > 5 * abs(estimate.value - truth)


def test_weighted_estimate_reads_the_weight_key(single_thread):
    """ŵ-weighted FQE through ``weight_key``: on the one-state problem every positive weighting has the same answer;
    a missing weight entry is a KeyError naming it."""
    data = _one_state_episodes(10, 5)
    data["density_ratio"] = torch.rand(data.shape[0], 1, generator=torch.Generator().manual_seed(1)) + 0.1
    policy = TensorDictModule(nn.Linear(1, 1), in_keys=["observation"], out_keys=["action"])
    weighted = estimate_offline_value(policy, data, gamma=0.5, horizon=5, weight_key="density_ratio", steps=1000,
                                      num_cells=(16,), lr=3e-3)
    assert weighted.weighted and weighted.value == pytest.approx(1.9375, abs=0.015)
    with pytest.raises(KeyError, match="ratio_typo"):
        estimate_offline_value(policy, data, gamma=0.5, horizon=5, weight_key="ratio_typo", steps=1)
