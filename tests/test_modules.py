"""Tests for torchrl_wbrm.modules: Q networks, the bounded actor, the bounded density-ratio network, maximisers."""
from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import Bounded, Unbounded

from torchrl_wbrm.modules import (
    PARAMETERISATIONS,
    ActorMaximiser,
    BoundedRatio,
    DensityRatioNetwork,
    GreedyDiscreteMaximiser,
    SampledActionMaximiser,
    make_deterministic_actor,
    make_discrete_q_network,
    make_q_network,
    max_q_over_candidates,
    uniform_actions,
)


class _NegativeSquaredDistance(nn.Module):
    """Q(x, a) = −(a − x)², maximised at a = x with value 0."""

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return -(action - observation).pow(2).sum(-1, keepdim=True)


def _known_q() -> TensorDictModule:
    return TensorDictModule(_NegativeSquaredDistance(), in_keys=["observation", "action"], out_keys=["state_action_value"])


# ---------------------------------------------------------------- BoundedRatio / DensityRatioNetwork
@pytest.mark.parametrize("parameterisation", PARAMETERISATIONS)
def test_bounded_ratio_is_one_at_zero_and_within_bounds(parameterisation):
    head = BoundedRatio((0.05, 20.0), parameterisation)
    assert head(torch.zeros(1)).item() == pytest.approx(1.0, rel=1e-6)
    extremes = head(torch.tensor([-1e4, -50.0, -3.0, 3.0, 50.0, 1e4]))
    assert (extremes >= 0.05 * (1 - 1e-6)).all() and (extremes <= 20.0 * (1 + 1e-6)).all()
    assert extremes[0].item() == pytest.approx(0.05, rel=1e-3)
    assert extremes[-1].item() == pytest.approx(20.0, rel=1e-3)
    assert (extremes.diff() >= 0).all()  # monotone


def test_soft_clamp_is_identity_in_log_space_near_zero_and_matches_design_formula():
    head = BoundedRatio((math.exp(-3.0), math.exp(3.0)), "soft_clamp")
    o = torch.linspace(-5, 5, 11)
    torch.testing.assert_close(head(o), torch.exp(3.0 * torch.tanh(o / 3.0)))  # w = exp(c·tanh(o/c))
    small = torch.tensor([1e-3, -1e-3])
    torch.testing.assert_close(torch.log(head(small)), small, rtol=1e-5, atol=1e-7)


def test_soft_clamp_keeps_gradient_where_hard_clamp_has_none():
    o = torch.tensor([8.0], requires_grad=True)  # exp(8) ≈ 2981 > Ψ = 1000
    BoundedRatio((1e-3, 1e3), "soft_clamp")(o).sum().backward()
    assert o.grad.item() > 0
    o.grad = None
    BoundedRatio((1e-3, 1e3), "hard_clamp")(o).sum().backward()
    assert o.grad.item() == 0


@pytest.mark.parametrize("bounds", [(0.0, 10.0), (1.5, 10.0), (0.1, 1.0), (0.1, float("inf")), (-1.0, 2.0)])
def test_bounded_ratio_rejects_bounds_outside_assumption_4_1(bounds):
    with pytest.raises(ValueError, match="0 < Φ < 1 < Ψ"):
        BoundedRatio(bounds)


def test_bounded_ratio_rejects_unknown_parameterisation():
    with pytest.raises(ValueError, match="parameterisation must be one of"):
        BoundedRatio((0.1, 10.0), "relu")


def test_density_ratio_network_output_key_shape_and_bounds():
    torch.manual_seed(0)
    net = DensityRatioNetwork(3, 2, bounds=(0.1, 10.0), num_cells=(16,))
    td = TensorDict({"observation": 100 * torch.randn(64, 3), "action": 100 * torch.randn(64, 2)}, [64])
    w = net(td)["density_ratio"]
    assert w.shape == (64, 1)
    assert (w >= 0.1 - 1e-6).all() and (w <= 10.0 + 1e-5).all()
    assert net.bounds == (0.1, 10.0)
    assert net.in_keys == ["observation", "action"] and net.out_keys == ["density_ratio"]
    small = TensorDict({"observation": 0.01 * torch.randn(8, 3), "action": torch.zeros(8, 2)}, [8])
    torch.testing.assert_close(net(small)["density_ratio"], torch.ones(8, 1), atol=0.05, rtol=0)  # starts near 1


def test_density_ratio_network_nested_keys():
    net = DensityRatioNetwork(2, 1, num_cells=(8,), in_keys=[("agent", "obs"), ("agent", "act")], out_key=("agent", "w"))
    td = TensorDict({"agent": {"obs": torch.randn(5, 2), "act": torch.randn(5, 1)}}, [5])
    assert net(td)["agent", "w"].shape == (5, 1)


# ---------------------------------------------------------------- Q networks and the actor
def test_q_network_initial_bias_and_shape():
    q = make_q_network(3, 2, num_cells=(8, 8), initial_bias=42.0)
    assert q.module[-1].bias.item() == 42.0
    td = TensorDict({"observation": torch.zeros(4, 3), "action": torch.zeros(4, 2)}, [4])
    value = q(td)["state_action_value"]
    assert value.shape == (4, 1)
    assert (value - 42.0).abs().max().item() < 5.0  # the bias dominates a fresh network's output


@pytest.mark.parametrize("action_space,action_shape", [("one-hot", (6, 3)), ("categorical", (6,))])
def test_discrete_q_network_greedy_action(action_space, action_shape):
    torch.manual_seed(0)
    q = make_discrete_q_network(4, 3, action_space=action_space, num_cells=(8,), initial_bias=-1.0)
    out = q(TensorDict({"observation": torch.randn(6, 4)}, [6]))
    assert out["action_value"].shape == (6, 3)
    assert out["action"].shape == action_shape
    torch.testing.assert_close(out["chosen_action_value"].squeeze(-1), out["action_value"].max(-1).values)
    with pytest.raises(ValueError, match="action_space must be"):
        make_discrete_q_network(4, 3, action_space="binary")


def test_deterministic_actor_stays_in_bounds():
    torch.manual_seed(0)
    spec = Bounded(torch.tensor([-1.0, 0.0]), torch.tensor([1.0, 3.0]), (2,))
    actor = make_deterministic_actor(3, spec, num_cells=(16,))
    action = actor(TensorDict({"observation": 1e3 * torch.randn(256, 3)}, [256]))["action"]
    assert action.shape == (256, 2)
    assert (action >= spec.space.low).all() and (action <= spec.space.high).all()
    assert action[:, 1].max() > 2.9 or action[:, 1].min() < 0.1  # saturates at the box for huge inputs
    with pytest.raises(ValueError, match="Bounded action spec"):
        make_deterministic_actor(3, Unbounded(2))


# ---------------------------------------------------------------- maximisers
def test_uniform_actions_shape_and_range():
    low, high = torch.tensor([-1.0, 2.0]), torch.tensor([1.0, 5.0])
    samples = uniform_actions(low, high, 1000, torch.Size([3]))
    assert samples.shape == (1000, 3, 2)
    assert (samples >= low).all() and (samples <= high).all()
    assert samples[..., 1].mean().item() == pytest.approx(3.5, abs=0.1)


def test_max_q_over_candidates_known_answer():
    q = _known_q()
    td = TensorDict({"observation": torch.tensor([[0.0], [0.5]])}, [2])
    candidates = torch.tensor([[[1.0], [1.0]], [[0.2], [0.4]], [[-1.0], [2.0]]])  # [K=3, B=2, A=1]
    best = max_q_over_candidates(q, td, candidates)
    torch.testing.assert_close(best, torch.tensor([-0.04, -0.01]))
    assert "action" not in td.keys()  # the input is not written to


def test_actor_and_sampled_maximisers():
    torch.manual_seed(0)
    q = _known_q()
    x = torch.rand(32, 1) * 2 - 1
    td = TensorDict({"observation": x}, [32])
    exact = ActorMaximiser()(q, td, actor_action=x)  # μ(x) = argmax
    torch.testing.assert_close(exact, torch.zeros(32))
    with pytest.raises(ValueError, match="actor_action"):
        ActorMaximiser()(q, td)
    sampled = SampledActionMaximiser(Bounded(-1.0, 1.0, (1,)), num_samples=256)
    approx = sampled(q, td)
    assert (approx <= 0).all() and approx.min().item() > -1e-3  # 256 uniform draws land close to the max
    torch.testing.assert_close(sampled(q, td, actor_action=x), torch.zeros(32))  # μ(x) is among the candidates
    with pytest.raises(ValueError, match="finite action bounds"):
        SampledActionMaximiser(Bounded(-float("inf"), 1.0, (1,)))


def test_greedy_discrete_maximiser():
    q = make_discrete_q_network(3, 4, num_cells=(8,))
    td = TensorDict({"observation": torch.randn(5, 3)}, [5])
    expected = q(td.copy())["action_value"].max(-1).values
    torch.testing.assert_close(GreedyDiscreteMaximiser()(q, td), expected)
    assert set(td.keys()) == {"observation"}
