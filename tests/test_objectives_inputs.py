"""Strict inputs of the LossModules (torchrl_wbrm.objectives), LQREnv.step and LQRConfig.

Each case asserts the error type and that the message names the key or shape.
"""
from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import ValueOperator
from torchrl.objectives import SoftUpdate

from torchrl_wbrm.envs import LQRConfig, LQREnv
from torchrl_wbrm.modules import DensityRatioNetwork
from torchrl_wbrm.objectives import MABOLoss, RobustDensityRatioLoss, WeightedBellmanLoss
from tests.references import Concat

GAMMA = 0.9


def _q(obs_dim=2, act_dim=1):
    torch.manual_seed(0)
    return ValueOperator(Concat(nn.Linear(obs_dim + act_dim, 1)), in_keys=["observation", "action"],
                         out_keys=["state_action_value"])


def _actor(obs_dim=2, act_dim=1):
    linear = nn.Linear(obs_dim, act_dim, bias=False)
    with torch.no_grad():
        linear.weight.fill_(-0.5)
    return TensorDictModule(linear, in_keys=["observation"], out_keys=["action"])


def _loss(cls=WeightedBellmanLoss, **kwargs):
    if cls is MABOLoss:
        critic = ValueOperator(Concat(nn.Linear(3, 1)), in_keys=["observation", "action"], out_keys=["adversary_weight"])
        loss = MABOLoss(_q(), critic, actor_network=_actor(), delay_value=True, **kwargs)
    else:
        loss = cls(_q(), actor_network=_actor(), delay_value=True, **kwargs)
    loss.make_value_estimator(gamma=GAMMA)
    SoftUpdate(loss, tau=0.1)
    return loss


def _data(n=8, flag_dtype=torch.bool) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    terminated = torch.zeros(n, 1, dtype=torch.bool)
    terminated[: n // 4] = True
    done = terminated.clone()
    done[n // 4 : n // 2] = True  # truncated
    return TensorDict(
        {
            "observation": torch.randn(n, 2, generator=g),
            "action": torch.rand(n, 1, generator=g) * 2 - 1,
            ("next", "observation"): torch.randn(n, 2, generator=g),
            ("next", "reward"): torch.randn(n, 1, generator=g),
            ("next", "done"): done.to(flag_dtype),
            ("next", "terminated"): terminated.to(flag_dtype),
            "density_ratio": torch.rand(n, 1, generator=g) * 2,
        },
        [n],
    )


# ---------------------------------------------------------------------- WeightedBellmanLoss (and MABO through it)
@pytest.mark.parametrize("dtype", [torch.int64, torch.int32, torch.uint8, torch.int8])
def test_integer_flags_give_the_bool_targets(dtype):
    loss = _loss()
    q_bool, y_bool = loss.bellman_error(_data())
    data = _data(flag_dtype=dtype)
    q_int, y_int = loss.bellman_error(data)
    torch.testing.assert_close(y_int, y_bool, rtol=0, atol=0)
    torch.testing.assert_close(q_int, q_bool, rtol=0, atol=0)
    assert data["next", "terminated"].dtype == dtype  # the input is not modified
    # and the target is r + γ V' exactly where not terminated, r where terminated
    terminated = _data()["next", "terminated"].squeeze(-1)
    reward = _data()["next", "reward"].squeeze(-1)
    assert torch.equal(y_int[terminated], reward[terminated])
    assert (y_int[~terminated] != reward[~terminated]).all()


def test_mabo_integer_flags_give_the_bool_targets():
    loss = _loss(MABOLoss, adversary="network")
    torch.testing.assert_close(loss.bellman_error(_data(flag_dtype=torch.uint8))[1], loss.bellman_error(_data())[1])


def test_float_or_non_binary_flags_are_refused():
    loss = _loss()
    with pytest.raises(TypeError, match=r"Entry \('next', 'done'\) is an episode-end flag of dtype torch.float32; pass bool"):
        loss(_data(flag_dtype=torch.float32))
    data = _data(flag_dtype=torch.int64)
    data["next", "done"][0] = 2
    with pytest.raises(ValueError, match=r"Entry \('next', 'done'\) .* values other than 0 and 1 \(min 0, max 2\)"):
        loss(data)


@pytest.mark.parametrize(
    "key, shape, pattern",
    [
        (("next", "observation"), (8, 3), r"Entry 'observation' has shape \(8, 2\) and \('next', 'observation'\) has shape \(8, 3\)"),
        (("next", "reward"), (8, 2), r"Entry \('next', 'reward'\) has shape \(8, 2\); expected .* \(8,\) or \(8, 1\)"),
        (("next", "terminated"), (8, 3), r"Entry \('next', 'terminated'\) has shape \(8, 3\)"),
        ("density_ratio", (8, 2), r"Entry 'density_ratio' has shape \(8, 2\)"),
    ],
)
def test_wrong_shapes_name_the_key_and_both_shapes(key, shape, pattern):
    data = _data()
    data.set(key, torch.ones(shape, dtype=data.get(key).dtype))
    with pytest.raises(ValueError, match=pattern):
        _loss()(data)


def test_empty_batch_and_non_finite_inputs_are_refused():
    loss = _loss()
    with pytest.raises(ValueError, match=r"The Bellman-residual batch is empty \(batch size \(0,\)\)"):
        loss(_data()[:0])
    for key in ("observation", ("next", "observation"), ("next", "reward"), "action"):
        data = _data()
        data.get(key)[2] = float("nan")
        with pytest.raises(ValueError, match=rf"Entry {key!r}".replace("(", r"\(").replace(")", r"\)") + r" holds \d+ non-finite"):
            loss(data)
    data = _data()
    data["density_ratio"][0] = float("inf")
    with pytest.raises(ValueError, match=r"Entry 'density_ratio' must be finite"):
        loss(data)


# ---------------------------------------------------------------------- RobustDensityRatioLoss
def _ratio_data(n_b=6, n_e=5, obs_b=2, obs_e=2):
    g = torch.Generator().manual_seed(1)
    def side(n, d):
        return TensorDict({"observation": torch.randn(n, d, generator=g), "action": torch.randn(n, 1, generator=g)}, [n])

    return TensorDict({"behaviour": side(n_b, obs_b), "expert": side(n_e, obs_e)}, [])


def _ratio_loss(**kwargs):
    torch.manual_seed(0)
    return RobustDensityRatioLoss(DensityRatioNetwork(2, 1, num_cells=(8,)), **kwargs)


@pytest.mark.parametrize("alpha", [math.inf, -math.inf, math.nan, 0.0, -1.0])
def test_ratio_alpha_must_be_finite_and_positive(alpha):
    with pytest.raises(ValueError, match=rf"alpha must be a finite number > 0 .*got {alpha!r}"):
        _ratio_loss(alpha=alpha)


def test_ratio_sides_must_have_the_same_feature_widths():
    with pytest.raises(ValueError, match=r"Entry \('behaviour', 'observation'\) has shape \(6, 2\) and \('expert', 'observation'\) has shape \(5, 3\)"):
        _ratio_loss()(_ratio_data(obs_e=3))


def test_ratio_empty_and_non_finite_inputs_are_refused():
    loss = _ratio_loss()
    with pytest.raises(ValueError, match=r"The 'expert' batch is empty"):
        loss(_ratio_data(n_e=0))
    data = _ratio_data()
    data["behaviour", "action"][1] = float("nan")
    with pytest.raises(ValueError, match=r"Entry \('behaviour', 'action'\) holds 1 non-finite"):
        loss(data)
    assert torch.isfinite(loss(_ratio_data())["loss_density_ratio"])


# ---------------------------------------------------------------------- LQREnv.step and LQRConfig
def test_lqr_step_checks_the_action():
    env = LQREnv("exp1", batch_size=[4], seed=0)
    td = env.reset()
    for action, error, pattern in [
        (torch.zeros(4, 3), ValueError, r"'action' has shape \(4, 3\), expected \(4, 2\)"),
        (torch.zeros(4), ValueError, r"'action' has shape \(4,\), expected \(4, 2\)"),
        (torch.zeros(4, 2, dtype=torch.float64), TypeError, r"'action' has dtype torch.float64, expected torch.float32"),
        (torch.tensor([[0.0, float("nan")]] * 4), ValueError, r"'action' holds 4 non-finite value\(s\)"),
    ]:
        with pytest.raises(error, match=pattern):
            env._step(td.clone().set("action", action))
    out = env.step(td.set("action", torch.zeros(4, 2)))
    assert torch.isfinite(out["next", "observation"]).all()


@pytest.mark.parametrize("name, value", [("F", [[math.nan, 0.0], [0.0, 0.5]]), ("G", [[math.inf, 0.0], [0.0, 0.5]]),
                                         ("R", [[0.25, 0.0], [0.0, math.nan]])])
def test_lqr_config_rejects_non_finite_matrices(name, value):
    with pytest.raises(ValueError, match=rf"LQRConfig.{name} must be finite"):
        LQRConfig(**{name: value})


def test_lqr_config_rejects_non_finite_numbers():
    with pytest.raises(ValueError, match=r"LQRConfig.reward_offset must be finite, got inf"):
        LQRConfig(reward_offset=math.inf)


def test_three_dimensional_exact_return_refusal_says_what_is_supported():
    cfg = dict(F=[[0.5, 0, 0], [0, 0.5, 0], [0, 0, 0.5]], G=[[0.5, 0], [0, 0.5], [0.2, 0.2]],
               S=[[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    with pytest.raises(NotImplementedError, match=r"rank <= 2, got rank 3 .*reward_clip=None"):
        LQREnv(LQRConfig(**cfg)).optimal_return()
    unclipped = LQREnv(LQRConfig(**cfg, reward_clip=None))
    assert math.isfinite(unclipped.optimal_return()) and unclipped.optimal_return() < 10 / (1 - 0.9)


# ---------------------------------------------------------------------- inputs accepted or named
def _typed_loss(**kwargs):
    from torchrl.data import Bounded

    from torchrl_wbrm.modules import make_deterministic_actor, make_q_network

    torch.manual_seed(0)
    spec = Bounded(-1.0, 1.0, (1,))
    loss = WeightedBellmanLoss(make_q_network(2, 1, num_cells=(8,), initial_bias=0.0),
                               actor_network=make_deterministic_actor(2, spec, num_cells=(8,)), **kwargs)
    loss.make_value_estimator(gamma=GAMMA)
    SoftUpdate(loss, tau=0.1)
    return loss


def test_reward_of_shape_b_with_flags_of_shape_b1_is_accepted():
    """reward [B] beside done/terminated [B, 1] (and the reverse): one value per sample either way, the same loss."""
    loss, data = _typed_loss(), _data()
    expected = loss(data.clone())["loss_value"]
    flat_reward = data.clone()
    flat_reward["next", "reward"] = data["next", "reward"].squeeze(-1)
    torch.testing.assert_close(loss(flat_reward)["loss_value"], expected)
    flat_flags = data.clone()
    for key in ("done", "terminated"):
        flat_flags["next", key] = data["next", key].squeeze(-1)
    torch.testing.assert_close(loss(flat_flags)["loss_value"], expected)


def test_float64_batch_with_float32_networks_names_key_and_dtypes():
    with pytest.raises(TypeError, match=r"Entry 'observation' has dtype torch.float64 but the value network's "
                                        r"parameters are torch.float32"):
        _typed_loss()(_data().apply(lambda x: x.double() if x.is_floating_point() else x))


def test_integer_weights_are_accepted():
    loss, data = _typed_loss(), _data()
    counts = torch.arange(8).reshape(8, 1) % 3
    as_ints, as_floats = data.clone(), data.clone()
    as_ints["density_ratio"], as_floats["density_ratio"] = counts, counts.float()
    ints, floats = loss(as_ints), loss(as_floats)
    torch.testing.assert_close(ints["loss_value"], floats["loss_value"])
    torch.testing.assert_close(ints["weight_ess"], floats["weight_ess"])


@pytest.mark.parametrize("key, width", [("observation", 3), ("action", 2)])
def test_an_input_width_other_than_the_network_is_named(key, width):
    data = _data()
    data[key] = torch.zeros(8, width)
    if key == "observation":
        data["next", key] = torch.zeros(8, width)
    with pytest.raises(ValueError, match=rf"The value network reads 3 input feature\(s\), but the batch gives 4: "
                                         rf".*'{key}' of shape \(8, {width}\) \({width} feature\(s\)\)"):
        _typed_loss()(data)


def test_discrete_action_index_out_of_range_is_named():
    from torchrl_wbrm.modules import make_discrete_q_network

    torch.manual_seed(0)
    loss = WeightedBellmanLoss(make_discrete_q_network(2, 3, num_cells=(8,), action_space="categorical"))
    loss.make_value_estimator(gamma=GAMMA)
    data = _data()
    data["action"] = torch.tensor([0, 1, 2, 5, 0, 1, 2, 0])
    with pytest.raises(ValueError, match=r"Entry 'action' holds action indices from 0 to 5; the Q head has 3 actions"):
        loss(data)
    data["action"] = torch.tensor([0, 1, 2, 2, 0, 1, 2, 0])
    assert torch.isfinite(loss(data)["loss_value"])


def test_all_zero_weights_are_refused_by_name():
    data = _data()
    data["density_ratio"] = torch.zeros(8, 1)
    with pytest.raises(ValueError, match=r"Every weight of the batch is 0 \(entry 'density_ratio'\)"):
        _typed_loss()(data)


@pytest.mark.parametrize("gamma", [math.nan, 1.5, -0.1, math.inf])
def test_value_estimator_gamma_outside_0_1_is_refused(gamma):
    with pytest.raises(ValueError, match=rf"gamma must be a finite number in \[0, 1\].*got {gamma!r}"):
        _typed_loss().make_value_estimator(gamma=gamma)


def test_ratio_width_other_than_the_network_is_named():
    with pytest.raises(ValueError, match=r"The ratio network reads 3 input feature\(s\), but the batch gives 4: "
                                         r"\('behaviour', 'observation'\) of shape \(6, 3\)"):
        _ratio_loss()(_ratio_data(obs_b=3, obs_e=3))
    with pytest.raises(TypeError, match=r"Entry \('behaviour', 'observation'\) has dtype torch.float64"):
        _ratio_loss()(_ratio_data().apply(lambda x: x.double()))
