"""Expert and behaviour policies, and the true density ratio between them."""
from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_wbrm.data import collect_transitions, episode_returns
from torchrl_wbrm.envs import LQREnv, make_lqr_env
from torchrl_wbrm.policies import (
    LinearGaussianPolicy,
    MountainCarHeuristic,
    lqr_true_density_ratio,
    make_lqr_behaviour,
    make_lqr_expert,
    make_lqr_optimal_policy,
    make_mountain_car_env,
    make_mountain_car_expert,
)


def test_expert_reading_of_the_paper():
    env = LQREnv("exp1")
    _, K = env.riccati()
    expert = make_lqr_expert(env, tau=0.05)
    torch.testing.assert_close(expert.module.gain, (0.95 * K).float())
    assert expert.module.noise_std == 0.05
    behaviour = make_lqr_behaviour(env)
    torch.testing.assert_close(behaviour.module.gain, (0.5 * K).float())
    assert behaviour.module.noise_std == 0.5
    with pytest.raises(ValueError, match="noise_std > 0"):
        make_lqr_behaviour(env, noise_std=0.0)
    with pytest.raises(ValueError, match="tau"):
        make_lqr_expert(env, tau=1.5)


def test_noise_and_deterministic_mode():
    pol = LinearGaussianPolicy(torch.eye(2), 0.5)
    x = torch.randn(20_000, 2)
    torch.manual_seed(0)
    a = pol(x)
    assert abs((a + x).std().item() - 0.5) < 0.01
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        torch.testing.assert_close(pol(x), -x)
    opt = make_lqr_optimal_policy(LQREnv("exp2"))
    td = opt(TensorDict(observation=torch.ones(3, 2), batch_size=[3]))
    torch.testing.assert_close(td["action"], LQREnv("exp2").optimal_action(torch.ones(3, 2)).float())


def test_measured_lqr_returns_are_ordered():
    env = make_lqr_env("exp1", batch_size=[2000], seed=0)
    returns = {}
    for name, pol in [("expert", make_lqr_expert(env)), ("behaviour", make_lqr_behaviour(env))]:
        data = collect_transitions(env, pol, 2000 * 20, seed=1)
        returns[name] = episode_returns(data, gamma=0.9).mean().item()
    optimum = env.base_env.optimal_return()
    assert returns["behaviour"] < returns["expert"] < optimum + 0.05
    assert optimum - returns["expert"] < 0.5  # the expert is near-optimal
    assert optimum - returns["behaviour"] > 1.0  # the behaviour policy is clearly poorer


@pytest.fixture(scope="module")
def ratio_samples():
    """Behaviour and expert samples (exp1, tau = 0.3 to keep the ratio's variance testable) and the ratio."""
    env = make_lqr_env("exp1", batch_size=[10_000], seed=3)
    expert, behaviour = make_lqr_expert(env, tau=0.3), make_lqr_behaviour(env)
    b = collect_transitions(env, behaviour, 200_000, seed=4)
    e = collect_transitions(env, expert, 200_000, seed=5)
    return lqr_true_density_ratio(env, expert, behaviour), b, e


def test_true_ratio_has_mean_one_under_behaviour(ratio_samples):
    ratio, b, _ = ratio_samples
    w = ratio(b.select("observation", "action").clone())["density_ratio"].double()
    se = w.std().item() / math.sqrt(len(w))
    assert abs(w.mean().item() - 1.0) < 3 * se, (w.mean().item(), se)


def test_true_ratio_reweights_behaviour_into_expert(ratio_samples):
    """E_b[w f] = E_e[f] for test functions f of (x, a): an independent check that uses the expert's samples."""
    ratio, b, e = ratio_samples
    w = ratio(b.select("observation", "action").clone())["density_ratio"].double().squeeze(-1)
    for f in (lambda td: td["action"][:, 0], lambda td: (td["observation"] ** 2).sum(-1), lambda td: td["action"][:, 1] * td["observation"][:, 1]):
        fb, fe = f(b).double(), f(e).double()
        est = (w * fb).mean().item()
        se = math.sqrt(((w * fb).var() / len(fb) + fe.var() / len(fe)).item())
        assert abs(est - fe.mean().item()) < 4 * se, (est, fe.mean().item(), se)


def test_true_ratio_matches_histogram_of_a_projection(ratio_samples):
    """On u = a_0 + 0.5 x_0, the marginal ratio p_e(u)/p_b(u) (histograms) equals E_b[w | u] (bin means of w)."""
    ratio, b, e = ratio_samples
    w = ratio(b.select("observation", "action").clone())["density_ratio"].double().squeeze(-1)
    proj = lambda td: (td["action"][:, 0] + 0.5 * td["observation"][:, 0]).double()  # noqa: E731
    ub, ue = proj(b), proj(e)
    edges = torch.linspace(-1.5, 1.5, 13, dtype=torch.float64)
    bin_b = torch.bucketize(ub, edges) - 1
    bin_e = torch.bucketize(ue, edges) - 1
    checked = 0
    for k in range(len(edges) - 1):
        nb, ne = (bin_b == k).sum().item(), (bin_e == k).sum().item()
        if nb < 2000 or ne < 2000:
            continue
        hist_ratio = (ne / len(ue)) / (nb / len(ub))
        mean_w = w[bin_b == k].mean().item()
        assert abs(hist_ratio - mean_w) / hist_ratio < 0.08, (k, hist_ratio, mean_w)
        checked += 1
    assert checked >= 4


def test_true_ratio_options_and_errors():
    env = LQREnv("exp1")
    e, b = make_lqr_expert(env), make_lqr_behaviour(env)
    r_uniform = lqr_true_density_ratio(env, e, b)
    r_disc = lqr_true_density_ratio(env, e, b, time_weights="discounted")
    x = 0.3 * torch.randn(5, 2)
    td = TensorDict(observation=x, action=env.optimal_action(x).float() + 0.05 * torch.randn(5, 2), batch_size=[5])
    w_uniform, w_disc = r_uniform(td.clone())["density_ratio"], r_disc(td.clone())["density_ratio"]
    assert not torch.allclose(w_uniform, w_disc)
    assert (w_uniform > 1).all()  # near the expert's actions the expert is far more likely
    log_w = r_uniform.module.log_ratio(x, 2 + td["action"])  # far off the expert's actions
    assert (log_w < -50).all() and log_w.dtype == torch.float64
    with pytest.raises(ValueError, match="time_weights"):
        lqr_true_density_ratio(env, e, b, time_weights="geometric")
    with pytest.raises(ValueError, match="degenerate"):
        lqr_true_density_ratio(env, make_lqr_optimal_policy(env), b)


def test_mountain_car_heuristic():
    pol = MountainCarHeuristic(power=1.0, tau=0.1)
    obs = torch.tensor([[-0.5, 0.01], [-0.5, -0.01], [-0.5, 0.0]])
    torch.manual_seed(0)
    a = pol(obs)
    assert (a.abs() <= 1).all()
    assert a[0].item() > 0.8 and a[1].item() < -0.8 and a[2].item() < -0.8
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        torch.testing.assert_close(pol(obs), torch.tensor([[1.0], [-1.0], [-1.0]]))
    with pytest.raises(ValueError, match="power"):
        MountainCarHeuristic(power=2.0)


def test_mountain_car_expert_reaches_the_goal():
    env = make_mountain_car_env(seed=0)
    torch.manual_seed(0)
    data = collect_transitions(env, make_mountain_car_expert(), 1500, seed=0)
    returns = episode_returns(data)
    assert len(returns) >= 5
    assert returns.mean().item() > 85  # its data's episodes return 93.50 (docs/results/paper_tables.md)


def test_true_ratio_follows_a_shifted_behaviour_start():
    """Behaviour episodes from x_0 ~ N(0, 2² I) (the expert's from the system's N(0, I)): the ratio that knows the
    shift reweights them into the expert's law (E_b[w f] = E_e[f]); the ratio that assumes the system's start does
    not (its E_b[w] is off by far more than its error), so a data shift the ratio ignored would be caught."""
    from dataclasses import replace

    # 5,000 systems x 20 steps: 100,000 transitions are whole episodes (the ratio mixes t = 0..19 uniformly)
    env = make_lqr_env("exp1", batch_size=[5_000], seed=3)
    shifted = make_lqr_env(replace(env.base_env.config, initial_std=2.0), batch_size=[5_000], seed=3)
    expert, behaviour = make_lqr_expert(env, tau=0.3), make_lqr_behaviour(env)
    b = collect_transitions(shifted, behaviour, 100_000, seed=4)
    e = collect_transitions(env, expert, 100_000, seed=5)
    x0 = b["observation"][b["step_count"].squeeze(-1) == 0]
    assert abs(x0.std().item() - 2.0) < 0.05  # the behaviour's episodes do start from the shifted law
    knows = lqr_true_density_ratio(env, expert, behaviour, behaviour_initial_std=2.0)
    ignores = lqr_true_density_ratio(env, expert, behaviour)
    sa = b.select("observation", "action")
    w = knows(sa.clone())["density_ratio"].double().squeeze(-1)
    for f in (lambda td: torch.ones(td.shape[0]), lambda td: (td["observation"] ** 2).sum(-1),
              lambda td: td["action"][:, 0] * td["observation"][:, 0]):
        fb, fe = f(b).double(), f(e).double()
        est = (w * fb).mean().item()
        se = math.sqrt(((w * fb).var() / len(fb) + fe.var() / len(fe)).item())
        assert abs(est - fe.mean().item()) < 4 * se, (est, fe.mean().item(), se)
    w_wrong = ignores(sa.clone())["density_ratio"].double().squeeze(-1)
    fb, fe = (b["observation"] ** 2).sum(-1).double(), (e["observation"] ** 2).sum(-1).double()
    se = math.sqrt(((w_wrong * fb).var() / len(fb) + fe.var() / len(fe)).item())
    assert abs((w_wrong * fb).mean().item() - fe.mean().item()) > 8 * se, ((w_wrong * fb).mean(), fe.mean(), se)
    with pytest.raises(ValueError, match="initial_std"):
        env.base_env.state_action_covariances(torch.zeros(2, 2), 0.5, initial_std=0.0)
