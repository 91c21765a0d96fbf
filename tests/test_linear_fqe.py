"""Least-squares FQE/FQI with Q linear in polynomial features, and the greedy policy of a quadratic Q: exact answers
on an LQR system with the unclipped reward (where the degree-2 class holds Q^π and Q*)."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from torchrl_wbrm.data.lqr import LQRDataConfig, make_lqr_datasets
from torchrl_wbrm.envs import LQRConfig, LQREnv
from torchrl_wbrm.evaluation import q_error
from torchrl_wbrm.evaluation.lqr_policy_value import linear_policy_q
from torchrl_wbrm.modules import PolynomialFeatures
from torchrl_wbrm.objectives import FQELoss
from torchrl_wbrm.ope import GreedyQuadraticPolicy, LinearQ, least_squares_fqe
from torchrl_wbrm.policies.lqr import LinearGaussianPolicy

UNCLIPPED = LQRConfig(reward_clip=None)


def _q_module(degree=2, initial=0.0):
    return TensorDictModule(LinearQ(2, 2, degree=degree, initial_value=initial), in_keys=["observation", "action"],
                            out_keys=["state_action_value"])


def _data(episodes=150, seed=0):
    return make_lqr_datasets(UNCLIPPED, LQRDataConfig(behaviour_episodes=2 * episodes, expert_episodes=2,
                                                      behaviour_noise_std=1.0), seed=seed).transitions[:]


def test_greedy_policy_of_q_star_is_the_optimal_gain():
    env = LQREnv(UNCLIPPED)
    _, K = env.riccati()
    q = LinearQ(2, 2, degree=2)
    z = torch.randn(500, 4, dtype=torch.float64)
    phi = q.features(z[:, :2], z[:, 2:])
    with torch.no_grad():
        q.theta.copy_(torch.linalg.lstsq(phi, env.optimal_q(z[:, :2], z[:, 2:]).squeeze(-1)).solution)
    greedy = GreedyQuadraticPolicy(q, 2, bound=5.0)
    x = torch.randn(64, 2)
    torch.testing.assert_close(greedy(x).double(), env.optimal_action(x.double()), atol=1e-4, rtol=0)
    far = torch.full((1, 2), 40.0)  # −Kx leaves the box: the best action is on its boundary
    assert float(greedy(far).detach().abs().max()) == pytest.approx(5.0)


def test_least_squares_fqe_recovers_q_pi_exactly_on_unclipped_lqr(single_thread):
    env = LQREnv(UNCLIPPED)
    _, K = env.riccati()
    gain = 0.8 * K
    policy = TensorDictModule(LinearGaussianPolicy(gain, 0.0), in_keys=["observation"], out_keys=["action"])
    data = _data()
    loss = FQELoss(_q_module(initial=90.0), policy)
    loss.make_value_estimator(gamma=env.config.gamma)
    info = least_squares_fqe(loss, data, PolynomialFeatures(2))
    assert info["converged"]
    x, a = torch.randn(1000, 2), torch.randn(1000, 2)
    q_hat = loss.q_value(TensorDict({"observation": x, "action": a}, [1000]))
    errors = q_error(q_hat, linear_policy_q(env, gain, 0.0, x.double(), a.double()))
    assert errors["relative_spread_error"] < 0.03  # measured 0.015: the data's noise (3,000 rows)
    # a weight of 0 drops a row: weighting out half of D gives the fit on the other half
    keep = torch.arange(data.shape[0]) % 2 == 0
    halves = []
    for w, rows in ((keep.double(), data), (None, data[keep])):
        half = FQELoss(_q_module(initial=90.0), policy)
        half.make_value_estimator(gamma=env.config.gamma)
        least_squares_fqe(half, rows, PolynomialFeatures(2), weight=w)
        halves.append(half.value_network_params.get(("module", "theta")).detach().clone())
    torch.testing.assert_close(halves[0], halves[1], rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="non-negative"):
        least_squares_fqe(loss, data, PolynomialFeatures(2), weight=-torch.ones(data.shape[0]))


def test_least_squares_fqi_finds_the_optimal_policy_on_unclipped_lqr(single_thread):
    env = LQREnv(UNCLIPPED)
    _, K = env.riccati()
    q = LinearQ(2, 2, degree=2, initial_value=90.0)
    greedy = GreedyQuadraticPolicy(LinearQ(2, 2, degree=2, initial_value=90.0), 2, bound=5.0)
    loss = FQELoss(TensorDictModule(q, in_keys=["observation", "action"], out_keys=["state_action_value"]),
                   TensorDictModule(greedy, in_keys=["observation"], out_keys=["action"]))
    loss.make_value_estimator(gamma=env.config.gamma)
    info = least_squares_fqe(loss, _data(), PolynomialFeatures(2), greedy=greedy)
    assert info["converged"]
    greedy.set_theta(loss.value_network_params.get(("module", "theta")))
    x = torch.randn(64, 2)
    torch.testing.assert_close(greedy(x).double(), env.optimal_action(x.double()), atol=0.06, rtol=0)  # measured 0.03
