"""Tests for RobustDensityRatioLoss (Section 3, "Density Ratio Estimation") and basu_power_divergence."""
from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn

from torchrl_wbrm.modules import DensityRatioNetwork
from torchrl_wbrm.objectives import RobustDensityRatioLoss, basu_power_divergence


class _Ratio(nn.Module):
    """A fixed ratio w(x) = scale · exp(x · direction − offset): no parameters except an optional scalar."""

    def __init__(self, direction: torch.Tensor, offset: float = 0.0, scale: float = 1.0) -> None:
        super().__init__()
        self.register_buffer("direction", direction)
        self.offset = offset
        self.log_scale = nn.Parameter(torch.tensor(math.log(scale)))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return torch.exp(observation @ self.direction - self.offset + self.log_scale).unsqueeze(-1)


def _ratio_module(direction, offset=0.0, scale=1.0, in_keys=("observation",), out_key="density_ratio"):
    return TensorDictModule(_Ratio(direction, offset, scale), in_keys=list(in_keys), out_keys=[out_key])


def _constant_ratio(c: float) -> TensorDictModule:
    return _ratio_module(torch.zeros(2), scale=c)


def _data(behaviour: torch.Tensor, expert: torch.Tensor) -> TensorDict:
    return TensorDict(
        {
            "behaviour": TensorDict({"observation": behaviour}, [behaviour.shape[0]]),
            "expert": TensorDict({"observation": expert}, [expert.shape[0]]),
        },
        [],
    )


def _random_data(n_behaviour=16, n_expert=12, d=2, seed=0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    return _data(torch.randn(n_behaviour, d, generator=g), torch.randn(n_expert, d, generator=g) + 0.5)


# ---------------------------------------------------------------- known answers
@pytest.mark.parametrize("c", [0.25, 1.0, 4.0])
@pytest.mark.parametrize(
    "alpha,expected",
    [
        (0.5, lambda c: c**1.5 - 3 * c**0.5),  # the paper's R̂ at α = ½
        (1.0, lambda c: c**2 - 2 * c),  # uLSIF
        (2.0, lambda c: c**3 - 1.5 * c**2),
        ("kl", lambda c: c - math.log(c)),  # α → 0
    ],
)
def test_constant_ratio_known_answer(alpha, expected, c):
    loss = RobustDensityRatioLoss(_constant_ratio(c), alpha=alpha)
    value = loss(_random_data())["loss_density_ratio"]
    assert value.item() == pytest.approx(expected(c), rel=1e-5, abs=1e-6)


def test_basu_known_answer_with_different_values_on_each_side():
    w_b, w_e = torch.tensor([1.0, 4.0]), torch.tensor([9.0])
    # mean_b w^{3/2} − 3 mean_e w^{1/2} = (1 + 8)/2 − 3·3
    assert basu_power_divergence(w_b, w_e, alpha=0.5).item() == pytest.approx(4.5 - 9.0)
    # relative β = ¼: ¼·27 + ¾·4.5 − 9
    assert basu_power_divergence(w_b, w_e, alpha=0.5, relative_beta=0.25).item() == pytest.approx(
        0.25 * 27 + 0.75 * 4.5 - 9.0
    )
    # D3RE, C = 0.1: |4.5 − 2.7| + 2.7 − 9 (bracket ≥ 0: equals the plain loss)
    assert basu_power_divergence(w_b, w_e, alpha=0.5, non_negative_correction=0.1).item() == pytest.approx(4.5 - 9.0)
    # C = 0.5: bracket 4.5 − 13.5 < 0 is replaced by its absolute value: 9 + 13.5 − 9
    assert basu_power_divergence(w_b, w_e, alpha=0.5, non_negative_correction=0.5).item() == pytest.approx(13.5)
    # reduction="none" pairs samples; its mean is the "mean" loss
    w_b2 = torch.tensor([1.0, 4.0])
    w_e2 = torch.tensor([9.0, 1.0])
    per_pair = basu_power_divergence(w_b2, w_e2, alpha=1.0, reduction="none")
    torch.testing.assert_close(per_pair, torch.tensor([1.0 - 18.0, 16.0 - 2.0]))
    assert per_pair.mean().item() == pytest.approx(basu_power_divergence(w_b2, w_e2, alpha=1.0).item())


def test_normalisation_penalty_known_answer():
    c = 2.0
    loss = RobustDensityRatioLoss(_constant_ratio(c), alpha=1.0, normalisation_coefficient=0.5)
    out = loss(_random_data())
    assert out["normalisation_penalty"].item() == pytest.approx((c - 1) ** 2)
    assert out["loss_density_ratio"].item() == pytest.approx(c**2 - 2 * c + 0.5 * (c - 1) ** 2)


def test_diagnostics_known_answer_and_detached():
    direction = torch.tensor([1.0, 0.0])
    loss = RobustDensityRatioLoss(_ratio_module(direction), alpha=0.5)
    behaviour, expert = torch.tensor([[0.0, 1.0], [1.0, 0.0]]), torch.tensor([[2.0, 0.0]])
    out = loss(_data(behaviour, expert))
    e = math.e
    assert out["density_ratio_behaviour_mean"].item() == pytest.approx((1 + e) / 2)
    assert out["density_ratio_expert_mean"].item() == pytest.approx(e**2)
    assert out["density_ratio_min"].item() == pytest.approx(1.0)
    assert out["density_ratio_max"].item() == pytest.approx(e**2)
    assert out["density_ratio_ess"].item() == pytest.approx((1 + e) ** 2 / (1 + e**2))
    assert out["loss_density_ratio"].requires_grad
    assert not any(v.requires_grad for k, v in out.items() if not k.startswith("loss_"))


# ---------------------------------------------------------------- the true ratio minimises the loss
def _shifted_gaussians(m: int, d: int, shift: float, seed: int):
    g = torch.Generator().manual_seed(seed)
    mean = torch.full((d,), shift)
    behaviour = torch.randn(m, d, generator=g)
    expert = torch.randn(m, d, generator=g) + mean
    return behaviour, expert, mean, 0.5 * float(mean @ mean)  # log w(x) = mean·x − |mean|²/2


@pytest.mark.usefixtures("single_thread")
@pytest.mark.parametrize("alpha", [0.5, 1.0, "kl"])
def test_true_ratio_has_lower_loss_than_perturbed_ratios(alpha):
    behaviour, expert, mean, offset = _shifted_gaussians(20_000, 2, 0.5, seed=1)
    data = _data(behaviour, expert)

    def value(direction, off, scale=1.0):
        return RobustDensityRatioLoss(_ratio_module(direction, off, scale), alpha=alpha)(data)["loss_density_ratio"]

    at_truth = value(mean, offset)
    perturbed = [
        value(mean, offset, scale=1.3),
        value(mean, offset, scale=0.7),
        value(1.4 * mean, offset),
        value(0.6 * mean, offset),
        value(mean + torch.tensor([0.3, -0.3]), offset),
        value(torch.zeros(2), 0.0),  # w ≡ 1
    ]
    for other in perturbed:
        assert at_truth.item() < other.item() - 1e-3


# ---------------------------------------------------------------- fitting closed-form Gaussian ratios
def _fit(net, behaviour, expert, *, steps, lr, alpha=0.5, seed=0):
    torch.manual_seed(seed)
    loss = RobustDensityRatioLoss(net, alpha=alpha)
    optimiser = torch.optim.Adam(loss.parameters(), lr=lr)
    data = _data(behaviour, expert)
    for _ in range(steps):  # full batch
        optimiser.zero_grad()
        loss(data)["loss_density_ratio"].backward()
        optimiser.step()
    return loss


def _relative_l2_error(net, samples, true_ratio):
    with torch.no_grad():
        w_hat = net(TensorDict({"observation": samples}, [samples.shape[0]]))["density_ratio"].squeeze(-1)
    w = true_ratio(samples)
    return (((w_hat - w) ** 2).mean().sqrt() / (w**2).mean().sqrt()).item(), w_hat.mean().item()


@pytest.mark.usefixtures("single_thread")
def test_fit_shifted_gaussians_relative_error_below_10_percent():
    """d = 4, m = 20k each, means 0 and 0.5 per dim: w(x) = exp(0.5·Σx − 0.5). A constant ŵ = 1 scores 79%."""
    torch.manual_seed(0)
    behaviour, expert, mean, offset = _shifted_gaussians(20_000, 4, 0.5, seed=0)
    # log-linear model: ŵ = soft_clamp(a·x + b) is exactly the true family inside the bounds
    net = DensityRatioNetwork(
        4, 0, num_cells=(), bounds=(1e-3, 1e3), parameterisation="soft_clamp", in_keys=["observation"]
    )
    _fit(net, behaviour, expert, steps=200, lr=0.05)
    fresh = torch.randn(20_000, 4, generator=torch.Generator().manual_seed(123))
    error, behaviour_mean = _relative_l2_error(net, fresh, lambda x: torch.exp(x @ mean - offset))
    assert error < 0.10  # measured 0.066
    assert behaviour_mean == pytest.approx(1.0, abs=0.05)


@pytest.mark.usefixtures("single_thread")
def test_fit_gaussian_covariance_ratio_with_an_mlp_below_10_percent():
    """d = 4, m = 20k each, N(0, 0.8 I) over N(0, I): w(x) = 0.8^{-2} exp(−|x|²/8). A constant ŵ = 1 scores 28%."""
    g = torch.Generator().manual_seed(0)
    behaviour = torch.randn(20_000, 4, generator=g)
    expert = math.sqrt(0.8) * torch.randn(20_000, 4, generator=g)
    torch.manual_seed(0)
    net = DensityRatioNetwork(4, 0, num_cells=(32,), bounds=(1e-3, 1e3), in_keys=["observation"])
    _fit(net, behaviour, expert, steps=300, lr=3e-3)
    fresh = torch.randn(20_000, 4, generator=torch.Generator().manual_seed(123))
    error, behaviour_mean = _relative_l2_error(net, fresh, lambda x: 0.8**-2 * torch.exp(-(x**2).sum(-1) / 8))
    assert error < 0.10  # measured 0.060 (default softplus output)
    assert behaviour_mean == pytest.approx(1.0, abs=0.05)


# ---------------------------------------------------------------- TorchRL conventions
def test_default_keys_and_out_keys():
    loss = RobustDensityRatioLoss(_constant_ratio(1.0))
    assert loss.tensor_keys.behaviour == "behaviour"
    assert loss.tensor_keys.expert == "expert"
    assert loss.tensor_keys.density_ratio == "density_ratio"
    assert set(loss.in_keys) == {("behaviour", "observation"), ("expert", "observation")}
    assert set(loss(_random_data()).keys()) == set(loss.out_keys)


def test_set_keys_and_nested_keys():
    net = _ratio_module(torch.tensor([1.0, 0.0]), in_keys=[("agent", "obs")], out_key=("agent", "w"))
    loss = RobustDensityRatioLoss(net, alpha=1.0)
    loss.set_keys(behaviour=("data", "b"), expert=("data", "e"), density_ratio=("agent", "w"))
    x_b, x_e = torch.randn(6, 2), torch.randn(4, 2)
    data = TensorDict(
        {"data": {"b": TensorDict({"agent": {"obs": x_b}}, [6]), "e": TensorDict({"agent": {"obs": x_e}}, [4])}}, []
    )
    expected = basu_power_divergence(torch.exp(x_b[:, 0]), torch.exp(x_e[:, 0]), alpha=1.0)
    torch.testing.assert_close(loss(data)["loss_density_ratio"], expected)
    assert ("data", "b", "agent", "obs") in loss.in_keys
    with pytest.raises(ValueError, match="not an accepted tensordict key"):
        loss.set_keys(weight="w")


def test_input_is_not_modified():
    loss = RobustDensityRatioLoss(DensityRatioNetwork(2, 0, num_cells=(8,), in_keys=["observation"]))
    data = _random_data()
    before = data.clone()
    loss(data)
    assert set(data.keys(True, True)) == set(before.keys(True, True))
    assert (data == before).all()


def test_backpropagates_only_into_the_ratio_network():
    torch.manual_seed(0)
    net = DensityRatioNetwork(2, 0, num_cells=(8,), in_keys=["observation"])
    loss = RobustDensityRatioLoss(net)
    data = _random_data()
    data["behaviour", "observation"].requires_grad_(False)
    loss(data)["loss_density_ratio"].backward()
    grads = [p.grad for p in loss.parameters()]
    assert len(grads) == 4 and all(g is not None and g.abs().sum() > 0 for g in grads)
    assert not list(loss.named_buffers(prefix="target"))  # no target network in stage 1


def test_reduction_none_keeps_the_batch_shape():
    loss = RobustDensityRatioLoss(_constant_ratio(4.0), alpha=0.5, reduction="none")
    out = loss(_random_data(10, 10))["loss_density_ratio"]
    assert out.shape == (10,)
    torch.testing.assert_close(out, torch.full((10,), 8.0 - 6.0))
    with pytest.raises(ValueError, match="batch sizes must match"):
        loss(_random_data(10, 9))


def test_reduction_sum():
    loss = RobustDensityRatioLoss(_constant_ratio(4.0), alpha=0.5, reduction="sum")
    assert loss(_random_data(10, 10))["loss_density_ratio"].item() == pytest.approx(10 * (8.0 - 6.0))


def test_state_dict_round_trip():
    torch.manual_seed(0)
    loss = RobustDensityRatioLoss(DensityRatioNetwork(2, 0, num_cells=(8,), in_keys=["observation"]))
    torch.manual_seed(1)
    other = RobustDensityRatioLoss(DensityRatioNetwork(2, 0, num_cells=(8,), in_keys=["observation"]))
    data = _random_data()
    assert loss(data)["loss_density_ratio"].item() != other(data)["loss_density_ratio"].item()
    other.load_state_dict(loss.state_dict())
    torch.testing.assert_close(other(data)["loss_density_ratio"], loss(data)["loss_density_ratio"])


# ---------------------------------------------------------------- bad inputs
def test_missing_sub_tensordict_or_input_key_is_a_key_error():
    loss = RobustDensityRatioLoss(_constant_ratio(1.0))
    data = _random_data()
    with pytest.raises(KeyError, match="Missing key .*expert.*sub-TensorDict of expert samples"):
        loss(data.exclude("expert"))
    with pytest.raises(KeyError, match="Missing key .*observation.*input of the ratio network, in the .*behaviour"):
        loss(TensorDict({"behaviour": TensorDict({"obs": torch.zeros(3, 2)}, [3]), "expert": data["expert"]}, []))
    loss.set_keys(density_ratio="ratio")
    with pytest.raises(KeyError, match="Missing key .*ratio.*the ratio network's output; its out_keys are"):
        loss(data)


def test_non_positive_ratio_is_a_value_error():
    net = TensorDictModule(lambda x: x[..., :1] - 10.0, in_keys=["observation"], out_keys=["density_ratio"])
    with pytest.raises(ValueError, match="'density_ratio' must be finite and strictly positive"):
        RobustDensityRatioLoss(net)(_random_data())


def test_wrong_ratio_shape_is_a_value_error():
    net = TensorDictModule(lambda x: torch.exp(x), in_keys=["observation"], out_keys=["density_ratio"])
    with pytest.raises(ValueError, match=r"shape \(16, 2\).*expected \(16,\) or \(16, 1\)"):
        RobustDensityRatioLoss(net)(_random_data())


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"alpha": 0.0}, "alpha must be"),
        ({"alpha": -1.0}, "alpha must be"),
        ({"alpha": "kullback"}, "alpha must be"),
        ({"relative_beta": 1.0}, "relative_beta"),
        ({"non_negative_correction": 0.0}, "non_negative_correction"),
        ({"normalisation_coefficient": -1.0}, "normalisation_coefficient"),
        ({"reduction": "max"}, "reduction must be"),
        ({"reduction": "none", "non_negative_correction": 0.1}, "reduction='none'"),
        ({"reduction": "none", "normalisation_coefficient": 1.0}, "reduction='none'"),
    ],
)
def test_bad_settings_are_value_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        RobustDensityRatioLoss(_constant_ratio(1.0), **kwargs)
