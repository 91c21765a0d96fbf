"""Tests for FQELoss (fitted Q evaluation of a given policy, optionally ŵ-weighted): TorchRL conventions and known
answers computed by hand."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType
from torchrl.modules import ValueOperator
from torchrl.objectives import HardUpdate, SoftUpdate

from torchrl_wbrm.objectives import FQELoss
from tests.references import Concat

GAMMA = 0.5


class _Constant(nn.Module):
    """Q(x, a) = c, one parameter: the one-state problem's whole class."""

    def __init__(self, value: float) -> None:
        super().__init__()
        self.c = nn.Parameter(torch.tensor([value]))

    def forward(self, observation, action):
        return self.c.expand(*observation.shape[:-1], 1)


def _constant_q(value: float = 0.0) -> ValueOperator:
    return ValueOperator(_Constant(value), in_keys=["observation", "action"], out_keys=["state_action_value"])


def _linear_q() -> ValueOperator:
    linear = nn.Linear(3, 1)
    with torch.no_grad():
        linear.weight.copy_(torch.tensor([[0.25, 0.5, 1.0]]))
        linear.bias.fill_(0.5)
    return ValueOperator(Concat(linear), in_keys=["observation", "action"], out_keys=["state_action_value"])


def _policy(scale: float = -1.0) -> TensorDictModule:
    """π(x) = scale · (x₁ + x₂), fixed."""
    linear = nn.Linear(2, 1, bias=False)
    with torch.no_grad():
        linear.weight.fill_(scale)
    return TensorDictModule(linear, in_keys=["observation"], out_keys=["action"])


def _batch(n: int = 4, *, seed: int = 0, terminated=None) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    term = torch.zeros(n, 1, dtype=torch.bool) if terminated is None else torch.as_tensor(terminated).reshape(n, 1)
    return TensorDict({
        "observation": torch.randn(n, 2, generator=g), "action": torch.randn(n, 1, generator=g),
        ("next", "observation"): torch.randn(n, 2, generator=g), ("next", "reward"): torch.randn(n, 1, generator=g),
        ("next", "done"): term.clone(), ("next", "terminated"): term,
    }, [n])


def _loss(q=None, policy=None, **kwargs) -> FQELoss:
    loss = FQELoss(_linear_q() if q is None else q, _policy() if policy is None else policy, **kwargs)
    loss.make_value_estimator(gamma=GAMMA)
    return loss


def _hand_q(x, a):
    return x @ torch.tensor([0.25, 0.5]) + 1.0 * a.squeeze(-1) + 0.5


# ---------------------------------------------------------------- known answers
def test_one_state_problem_by_hand():
    """One state, one action, r = 1, γ = ½: Q^π = 1 / (1 − γ) = 2 (no termination), 1 (terminated). The loss at
    c is (c − 1 − γ c̄)² with c̄ the target's copy; iterating FQE (hard target update each step) converges to 2."""
    data = TensorDict({"observation": torch.zeros(1, 1), "action": torch.zeros(1, 1),
                       ("next", "observation"): torch.zeros(1, 1), ("next", "reward"): torch.ones(1, 1),
                       ("next", "done"): torch.zeros(1, 1, dtype=torch.bool),
                       ("next", "terminated"): torch.zeros(1, 1, dtype=torch.bool)}, [1])
    policy = TensorDictModule(nn.Linear(1, 1), in_keys=["observation"], out_keys=["action"])
    loss = _loss(_constant_q(0.5), policy)
    assert loss(data.clone())["loss_value"].item() == pytest.approx((0.5 - 1 - 0.5 * 0.5) ** 2)
    updater = HardUpdate(loss, value_network_update_interval=1)
    optim = torch.optim.SGD(loss.value_network_params.values(True, True), lr=0.5)  # c ← Y exactly (∂ℓ/∂c = 2(c − Y))
    for _ in range(60):
        optim.zero_grad()
        loss(data.clone())["loss_value"].backward()
        optim.step()
        updater.step()
    assert loss.value_network_params["module", "c"].item() == pytest.approx(2.0, abs=1e-6)
    data["next", "terminated"] = torch.ones(1, 1, dtype=torch.bool)
    for _ in range(3):
        optim.zero_grad()
        loss(data.clone())["loss_value"].backward()
        optim.step()
    assert loss.value_network_params["module", "c"].item() == pytest.approx(1.0, abs=1e-6)


def test_loss_matches_hand_computation_with_policy_action():
    data = _batch(5, terminated=[False, True, False, False, True])
    loss = _loss()
    out = loss(data.clone())
    x, a, x1 = data["observation"], data["action"], data["next", "observation"]
    pi = -(x1.sum(-1, keepdim=True))
    target = data["next", "reward"].squeeze(-1) + GAMMA * (~data["next", "terminated"].squeeze(-1)) * _hand_q(x1, pi)
    delta = _hand_q(x, a) - target
    torch.testing.assert_close(out["loss_value"], delta.pow(2).mean())
    torch.testing.assert_close(out["td_error_mean"], delta.mean())


def test_weighted_reduction_is_torchrl_sum_w_l_over_sum_w():
    data = _batch(4)
    data["density_ratio"] = torch.tensor([[2.0], [0.0], [1.0], [1.0]])
    data["priority_weight"] = torch.tensor([1.0, 3.0, 2.0, 1.0])
    loss = _loss(use_weights=True)
    per_sample = _loss(reduction="none", use_prioritized_weights=False)(data.clone())
    squared = data.clone()
    _loss(use_prioritized_weights=False)(squared)
    delta2 = squared["td_error"].squeeze(-1)
    w = torch.tensor([2.0, 0.0, 2.0, 1.0])
    torch.testing.assert_close(loss(data.clone())["loss_value"], (w * delta2).sum() / w.sum())
    assert per_sample["loss_value"].shape == (4,)
    torch.testing.assert_close(per_sample["loss_value"], delta2)
    with pytest.raises(KeyError, match="density_ratio"):
        loss(_batch(4))


def test_mask_drops_rows():
    data = _batch(4)
    data["collector", "mask"] = torch.tensor([True, False, True, True])
    full = data.exclude(("collector", "mask"))
    out = _loss()(data.clone())
    kept = _loss()(full[torch.tensor([0, 2, 3])].clone())
    torch.testing.assert_close(out["loss_value"], kept["loss_value"])
    data["collector", "mask"][1] = True
    data["next", "reward"][1] = float("nan")  # a NaN in a masked row must not reach the loss
    data["collector", "mask"][1] = False
    assert torch.isfinite(_loss()(data.clone())["loss_value"])


# ---------------------------------------------------------------- TorchRL conventions
def test_set_keys_nested_and_unknown():
    data = _batch(3)
    data.rename_key_("action", ("agent", "act"))
    data["w"] = torch.ones(3)
    q = ValueOperator(Concat(nn.Linear(3, 1)), in_keys=["observation", ("agent", "act")], out_keys=["q"])
    policy = TensorDictModule(nn.Linear(2, 1), in_keys=["observation"], out_keys=[("agent", "act")])
    loss = FQELoss(q, policy, use_weights=True)
    loss.set_keys(action=("agent", "act"), state_action_value="q", weight="w")
    loss.make_value_estimator(gamma=GAMMA)
    assert torch.isfinite(loss(data)["loss_value"])
    assert ("agent", "act") in loss.in_keys and "w" in loss.in_keys
    with pytest.raises(ValueError, match="not an accepted tensordict key"):
        loss.set_keys(nonsense="x")


def test_input_not_modified_except_td_error_and_policy_not_trained():
    data = _batch(4)
    before = data.clone()
    loss = _loss()
    loss(data)["loss_value"].backward()
    assert set(data.keys(True, True)) - set(before.keys(True, True)) == {"td_error"}
    assert (data == before.update({"td_error": data["td_error"]})).all()
    assert all(p.grad is None for p in loss.policy_network_params.values(True, True))
    assert all(p.grad is None for p in loss.target_value_network_params.values(True, True))
    assert all(p.grad is not None for p in loss.value_network_params.values(True, True))


@pytest.mark.parametrize("updater", ["soft", "hard"])
def test_target_params_change_only_with_updater(updater):
    loss = _loss()
    upd = SoftUpdate(loss, tau=0.5) if updater == "soft" else HardUpdate(loss, value_network_update_interval=1)
    optim = torch.optim.SGD(loss.value_network_params.values(True, True), lr=0.1)
    target = loss.target_value_network_params.clone()
    optim.zero_grad()
    loss(_batch(8))["loss_value"].backward()
    optim.step()
    assert (loss.target_value_network_params == target).all()
    for _ in range(1 if updater == "soft" else 2):  # HardUpdate copies on the step after `interval` steps
        upd.step()
    assert not (loss.target_value_network_params == target).all()


def test_delay_value_false_bootstraps_on_online_params_detached():
    data = _batch(4)
    loss = _loss(delay_value=False)
    q_value, target = loss.bellman_error(data)
    assert not target.requires_grad and q_value.requires_grad
    with torch.no_grad():
        for p in loss.value_network_params.values(True, True):
            p.add_(1.0)  # the bootstrap follows the online parameters at once
    assert not torch.allclose(loss.bellman_error(data)[1], target)


def test_random_exploration_draws_from_a_stochastic_policy():
    class Noisy(nn.Module):
        def forward(self, observation):
            from torchrl.envs.utils import exploration_type
            noise = torch.randn(*observation.shape[:-1], 1) if exploration_type() == ExplorationType.RANDOM else 0.0
            return observation.sum(-1, keepdim=True) * 0 + noise

    policy = TensorDictModule(Noisy(), in_keys=["observation"], out_keys=["action"])
    data = _batch(64)
    det = _loss(policy=policy).policy_action(data["next"])
    assert (det == 0).all()
    rnd = _loss(policy=policy, exploration_type=ExplorationType.RANDOM).policy_action(data["next"])
    assert rnd.std() > 0.5


def test_state_dict_round_trip_and_bad_settings():
    loss, other = _loss(), _loss()
    with torch.no_grad():
        for p in other.value_network_params.values(True, True):
            p.add_(1.0)
    assert other(_batch(3))["loss_value"] != loss(_batch(3))["loss_value"]
    other.load_state_dict(loss.state_dict())
    torch.testing.assert_close(other(_batch(3))["loss_value"], loss(_batch(3))["loss_value"])
    with pytest.raises(ValueError, match="gamma"):
        loss.make_value_estimator(gamma=1.5)
    with pytest.raises(ValueError, match="reduction"):
        FQELoss(_linear_q(), _policy(), reduction="avg")
    with pytest.raises(TypeError, match="TensorDictModule"):
        FQELoss(_linear_q(), nn.Linear(2, 1))


def test_stacked_parameters_under_vmap():
    """An ensemble of FQE losses as one vmapped call over stacked parameters (TorchRL's pattern)."""
    loss = _loss()
    data = _batch(8)
    base = TensorDict.from_module(loss)
    stacked = torch.stack([base.data.clone().apply(lambda t: t + 0.1 * i) for i in range(3)])

    def one(params):
        with params.to_module(loss):
            return loss(data.clone())["loss_value"]

    batched = torch.vmap(one)(stacked)
    looped = torch.stack([one(stacked[i]) for i in range(3)])
    torch.testing.assert_close(batched, looped)
    assert looped.unique().numel() == 3
