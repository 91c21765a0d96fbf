"""WeightedLoss: ŵ as the per-sample weight of torchrl's losses, with known answers for every loss of torchrl 0.14.1
that supports ``reduction="none"``; and which of them read ``"priority_weight"`` natively."""
from __future__ import annotations

import inspect
import re
import warnings
from pathlib import Path

import pytest
import torch
import torchrl.objectives as tro
from tensordict import TensorDict
from torchrl.data import Bounded
from tensordict.nn import TensorDictModule
from torchrl.modules import OneHotCategorical, ProbabilisticActor, ValueOperator
from torchrl.objectives import LossModule, SoftUpdate

from torchrl_wbrm.modules import (
    build_mlp,
    make_deterministic_actor,
    make_discrete_q_network,
    make_q_network,
    make_tanh_normal_actor,
)
from torchrl_wbrm.objectives import NATIVE_PRIORITY_WEIGHT_LOSSES, WeightedLoss, reads_priority_weight

ROOT = Path(__file__).resolve().parents[1]
OBS, ACT, NUM_ACTIONS, B = 3, 2, 4, 8
SPEC = Bounded(-1.0, 1.0, (ACT,))


def _q():
    return make_q_network(OBS, ACT, num_cells=(8,), initial_bias=0.0)


def _v():
    return ValueOperator(build_mlp(OBS, 1, num_cells=(8,)), in_keys=["observation"], out_keys=["state_value"])


def _stochastic_actor():
    return make_tanh_normal_actor(OBS, SPEC, num_cells=(8,))


def _actor():
    return make_deterministic_actor(OBS, SPEC, num_cells=(8,))


def _discrete_q():
    return make_discrete_q_network(OBS, NUM_ACTIONS, num_cells=(8,))


def _categorical_actor():
    logits = TensorDictModule(build_mlp(OBS, NUM_ACTIONS, num_cells=(8,)), in_keys=["observation"], out_keys=["logits"])
    return ProbabilisticActor(logits, in_keys=["logits"], distribution_class=OneHotCategorical)


def _action_values():
    return ValueOperator(build_mlp(OBS, NUM_ACTIONS, num_cells=(8,)), in_keys=["observation"],
                         out_keys=["action_value"])


def _kw(reduction):
    """``reduction`` (and ``scalar_output_mode="exclude"``, which torchrl wants beside ``"none"``), or nothing: the
    loss as a user builds it by default."""
    return {} if reduction is None else {"reduction": reduction, "scalar_output_mode": "exclude"}


#: name -> (builder(reduction; None: torchrl's defaults), discrete data?, draws random numbers in forward?)
LOSSES = {
    "IQLLoss": (lambda r: tro.IQLLoss(_stochastic_actor(), _q(), _v(), **_kw(r)),
                False, False),
    "CQLLoss": (lambda r: tro.CQLLoss(_stochastic_actor(), _q(), **_kw(r)),
                False, True),
    "DiscreteCQLLoss": (lambda r: tro.DiscreteCQLLoss(_discrete_q(), action_space="one-hot", reduction=r), True, False),
    "SACLoss": (lambda r: tro.SACLoss(_stochastic_actor(), _q(), **_kw(r)),
                False, True),
    "TD3Loss": (lambda r: tro.TD3Loss(_actor(), _q(), action_spec=SPEC, reduction=r), False, True),
    "TD3BCLoss": (lambda r: tro.TD3BCLoss(_actor(), _q(), action_spec=SPEC, reduction=r), False, True),
    "DDPGLoss": (lambda r: tro.DDPGLoss(_actor(), _q(), reduction=r), False, False),
    "DQNLoss": (lambda r: tro.DQNLoss(_discrete_q(), action_space="one-hot", reduction=r), True, False),
    "BCLoss": (lambda r: tro.BCLoss(_actor(), loss_function="l2", reduction=r), False, False),
    "DiscreteSACLoss": (lambda r: tro.DiscreteSACLoss(_categorical_actor(), _action_values(), num_actions=NUM_ACTIONS,
                                                      **_kw(r)), True, False),
}
# Not here: DiscreteIQLLoss (torchrl 0.14.1's forward fails on a one-hot categorical actor), CQLLoss with
# with_lagrange=True (refused, below), and the on-policy / model-based losses.


def _build(name: str, reduction: str) -> LossModule:
    torch.manual_seed(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no target network updater": these tests call the loss only
        return LOSSES[name][0](reduction)


def _data(name: str, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    if LOSSES[name][1]:
        action = torch.nn.functional.one_hot(torch.randint(NUM_ACTIONS, (B,), generator=g), NUM_ACTIONS)
    else:
        action = torch.rand(B, ACT, generator=g) * 2 - 1
    return TensorDict({
        "observation": torch.randn(B, OBS, generator=g),
        "action": action,
        ("next", "observation"): torch.randn(B, OBS, generator=g),
        ("next", "reward"): torch.randn(B, 1, generator=g),
        ("next", "done"): torch.zeros(B, 1, dtype=torch.bool),
        ("next", "terminated"): torch.zeros(B, 1, dtype=torch.bool),
    }, [B])


def _call(loss, td, seed=1):
    torch.manual_seed(seed)  # the same random state for losses that sample (CQL, SAC, TD3's target noise)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return loss(td.clone())


def _terms(out) -> dict:
    return {k: out[k] for k in out.keys() if k == "loss" or k.startswith("loss_")}


def _per_sample(value: torch.Tensor) -> torch.Tensor:
    return value.reshape(B, -1).mean(-1)


@pytest.fixture(params=list(LOSSES))
def name(request):
    return request.param


@pytest.fixture(params=["none", None], ids=["built_none", "built_default"])
def how(request):
    """How the wrapped loss is built: with ``reduction="none"``, or with torchrl's defaults (``"mean"``), which
    WeightedLoss switches to per-sample terms itself."""
    return request.param


def test_every_loss_has_terms(name, how):
    out = _call(WeightedLoss(_build(name, how)), _data(name).set("density_ratio", torch.ones(B)))
    assert _terms(out) and all(v.shape == () for v in _terms(out).values()), out


def test_constant_weights_give_the_unweighted_loss(name, how):
    td = _data(name)
    plain = _terms(_call(_build(name, "mean"), td))
    weighted = _terms(_call(WeightedLoss(_build(name, how)), td.set("density_ratio", torch.full((B,), 3.0))))
    assert plain.keys() == weighted.keys()
    for key in plain:
        torch.testing.assert_close(weighted[key], plain[key], rtol=1e-5, atol=1e-6, msg=key)


def test_doubling_every_weight_changes_nothing(name, how):
    w = torch.rand(B, generator=torch.Generator().manual_seed(3)) + 0.1
    loss = WeightedLoss(_build(name, how))
    one = _terms(_call(loss, _data(name).set("density_ratio", w)))
    two = _terms(_call(loss, _data(name).set("density_ratio", 2 * w)))
    for key in one:
        torch.testing.assert_close(two[key], one[key], rtol=1e-5, atol=1e-6, msg=key)


def test_weighted_mean_of_the_per_sample_terms(name, how):
    """Σ wᵢ lᵢ / Σ wᵢ, with lᵢ the unwrapped loss's reduction="none" terms under the same random state."""
    w = torch.rand(B, 1, generator=torch.Generator().manual_seed(4))
    td = _data(name)
    per_sample = _terms(_call(_build(name, "none"), td))
    weighted = _terms(_call(WeightedLoss(_build(name, how)), td.set("density_ratio", w)))
    for key, value in per_sample.items():
        expected = (_per_sample(value) * w.squeeze(-1)).sum() / w.sum()
        torch.testing.assert_close(weighted[key], expected, rtol=1e-5, atol=1e-6, msg=key)


def test_zero_one_weights_give_the_loss_on_the_selected_rows(name, how):
    """0/1 weights: the unwrapped loss on the rows of weight 1. A loss that draws random numbers draws them for the
    whole batch, so it is compared with its per-sample terms on those rows under the same random state; the others
    with the unwrapped loss (reduction="mean") run on the selected rows alone."""
    keep = torch.tensor([1, 0, 1, 1, 0, 0, 1, 0], dtype=torch.bool)
    td = _data(name)
    weighted = _terms(_call(WeightedLoss(_build(name, how)), td.set("density_ratio", keep.float())))
    if LOSSES[name][2]:
        expected = {k: _per_sample(v)[keep].mean() for k, v in _terms(_call(_build(name, "none"), td)).items()}
    else:
        expected = _terms(_call(_build(name, "mean"), td[keep]))
    assert expected.keys() == weighted.keys()
    for key in expected:
        torch.testing.assert_close(weighted[key], expected[key], rtol=1e-5, atol=1e-6, msg=key)


def test_priority_weight_multiplies_once(name, how):
    """ŵ times the batch's "priority_weight": Σ ŵp l / Σ ŵp, for losses that read it natively (no double weighting)
    and for those that do not; with ŵ ≡ 1, a native loss gives its own priority-weighted loss."""
    g = torch.Generator().manual_seed(5)
    w, p = torch.rand(B, generator=g) + 0.1, torch.rand(B, generator=g) + 0.1
    td = _data(name)
    per_sample = _terms(_call(_build(name, "none"), td))  # no priority_weight in td: unweighted terms
    loss = WeightedLoss(_build(name, how))
    weighted = _terms(_call(loss, td.clone().set("density_ratio", w).set("priority_weight", p)))
    for key, value in per_sample.items():
        expected = (_per_sample(value) * w * p).sum() / (w * p).sum()
        torch.testing.assert_close(weighted[key], expected, rtol=1e-5, atol=1e-6, msg=key)
    if name in NATIVE_PRIORITY_WEIGHT_LOSSES:
        native = _terms(_call(_build(name, "mean"), td.clone().set("priority_weight", p)))
        only_p = _terms(_call(loss, td.clone().set("density_ratio", torch.ones(B)).set("priority_weight", p)))
        for key in native:
            if name == "TD3BCLoss" and key == "loss_actor":
                continue  # torchrl weights only −λQ there (its cloning term is an unweighted batch mean)
            torch.testing.assert_close(only_p[key], native[key], rtol=1e-5, atol=1e-6, msg=key)


# ---------------------------------------------------------------- which losses read "priority_weight" natively
def _loss_classes():
    return {n: c for n, c in vars(tro).items() if isinstance(c, type) and issubclass(c, LossModule)
            and c is not LossModule}


def test_native_priority_weight_list_matches_torchrl_source():
    """The losses whose own source reads the priority weight (``_maybe_get_priority_weight`` or the
    ``priority_weight`` key) are exactly the documented list."""
    native = sorted(n for n, c in _loss_classes().items()
                    if re.search(r"_maybe_get_priority_weight|tensor_keys\.priority_weight", inspect.getsource(c)))
    assert native == sorted(NATIVE_PRIORITY_WEIGHT_LOSSES)


def test_native_priority_weight_list_matches_behaviour(name):
    """A non-uniform "priority_weight" changes the unwrapped loss exactly for the losses of the list."""
    td = _data(name)
    p = torch.rand(B, generator=torch.Generator().manual_seed(6)) * 10
    loss = _build(name, "mean")
    plain = _terms(_call(loss, td))
    prioritised = _terms(_call(loss, td.clone().set("priority_weight", p)))
    changed = any(not torch.allclose(plain[k], prioritised[k]) for k in plain)
    assert changed == (name in NATIVE_PRIORITY_WEIGHT_LOSSES), name
    assert reads_priority_weight(_build(name, "none")) == (name in NATIVE_PRIORITY_WEIGHT_LOSSES)


def test_docs_name_the_native_losses_and_no_others():
    """store_density_ratio's docs and the reuse tutorial's "The pieces" name the native list, and name IQLLoss and
    CQLLoss only as losses that need WeightedLoss."""
    import torchrl_wbrm.ratio.storing as storing

    page = (ROOT / "docs" / "tutorials" / "torchrl_agent.md").read_text()
    section = page.split("## The pieces", 1)[1].split("\n## ", 1)[0]
    for text in (storing.__doc__ + store_density_ratio_doc(), section):
        listed = re.search(r"read\w*\s+``?\"priority_weight\"``?\s+(?:themselves|natively)[^.]*?\(([^)]*)\)", text)
        assert listed, text[:400]
        assert sorted(re.findall(r"(\w+Loss)", listed.group(1))) == sorted(NATIVE_PRIORITY_WEIGHT_LOSSES)
        assert re.search(r"IQLLoss[^.]*WeightedLoss", text), text[:400]


def store_density_ratio_doc() -> str:
    from torchrl_wbrm.ratio import store_density_ratio

    return store_density_ratio.__doc__


# ---------------------------------------------------------------- refusals, keys, targets, estimator
def test_a_loss_built_with_the_default_reduction_gives_per_sample_terms_to_the_wrapper():
    torch.manual_seed(0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no reduction="none" warning: the wrapper sets scalar_output_mode itself
        iql = tro.IQLLoss(_stochastic_actor(), _q(), _v())
        assert iql.reduction == "mean"
        loss = WeightedLoss(iql)
    assert iql.reduction == "none" and iql.scalar_output_mode == "exclude"
    td = _data("IQLLoss")
    w = torch.rand(B, generator=torch.Generator().manual_seed(6)) + 0.1
    weighted = _terms(_call(loss, td.clone().set("density_ratio", w)))
    per_sample = _terms(_call(_build("IQLLoss", "none"), td))
    assert weighted.keys() == per_sample.keys() == {"loss_actor", "loss_qvalue", "loss_value"}
    for key, value in per_sample.items():
        torch.testing.assert_close(weighted[key], (_per_sample(value) * w).sum() / w.sum(), msg=key)
    with pytest.raises(ValueError, match=r"reduction must be one of"):
        bad = _build("BCLoss", None)
        bad.reduction = "median"
        WeightedLoss(bad)


def test_refuses_a_batch_level_term_at_construction():
    torch.manual_seed(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cql = tro.CQLLoss(_stochastic_actor(), _q(), reduction="none", scalar_output_mode="exclude", with_lagrange=True)
    with pytest.raises(ValueError, match=r"CQLLoss\(with_lagrange=True\).*'loss_alpha_prime'"):
        WeightedLoss(cql)


def test_refuses_a_loss_without_reduction():
    class NoReduction(LossModule):
        def forward(self, td):
            return TensorDict({"loss_x": td["x"].mean()}, [])

    with pytest.raises(ValueError, match=r"NoReduction has no 'reduction' setting"):
        WeightedLoss(NoReduction())


def test_a_term_without_the_batch_shape_is_named():
    class Scalar(LossModule):
        reduction = "none"
        in_keys, out_keys = ["x"], ["loss_x"]

        def forward(self, td):
            return TensorDict({"loss_x": td["x"].mean()}, [])

    td = TensorDict({"x": torch.ones(4), "density_ratio": torch.ones(4)}, [4])
    with pytest.raises(ValueError, match=r"Scalar returned 'loss_x' of shape \(\)"):
        WeightedLoss(Scalar())(td)


def test_weights_are_checked_by_name():
    loss = WeightedLoss(_build("DDPGLoss", "none"))
    td = _data("DDPGLoss")
    with pytest.raises(KeyError, match="density_ratio"):
        _call(loss, td)
    with pytest.raises(ValueError, match=r"Every weight of the batch is 0 \(entry 'density_ratio'\)"):
        _call(loss, td.clone().set("density_ratio", torch.zeros(B)))
    with pytest.raises(ValueError, match="'density_ratio' must be finite and non-negative"):
        _call(loss, td.clone().set("density_ratio", -torch.ones(B)))
    with pytest.raises(ValueError, match=r"'density_ratio' has shape \(8, 2\)"):
        _call(loss, td.clone().set("density_ratio", torch.ones(B, 2)))
    ints = _terms(_call(loss, td.clone().set("density_ratio", torch.arange(B) % 3)))
    floats = _terms(_call(loss, td.clone().set("density_ratio", (torch.arange(B) % 3).float())))
    for key in floats:
        torch.testing.assert_close(ints[key], floats[key])


def test_set_keys_reach_the_wrapped_loss():
    loss = WeightedLoss(_build("DDPGLoss", "none"), weight_key="w")
    loss.set_keys(reward="r", weight="w2")
    assert loss.loss_module.tensor_keys.reward == "r" and loss.tensor_keys.weight == "w2"
    with pytest.raises(ValueError, match="not_a_key is not an accepted tensordict key"):
        loss.set_keys(not_a_key="x")
    td = _data("DDPGLoss")
    td.rename_key_(("next", "reward"), ("next", "r"))
    out = _call(loss, td.set("w2", torch.ones(B)))
    assert torch.isfinite(out["loss_value"])
    assert "w2" in loss.in_keys and ("next", "r") in loss.in_keys


def test_targets_state_and_value_estimator_are_the_wrapped_loss():
    inner = _build("DDPGLoss", "none")
    loss = WeightedLoss(inner)
    assert loss.state_dict().keys() == inner.state_dict().keys()
    assert {id(p) for p in loss.parameters()} == {id(p) for p in inner.parameters()}
    loss.make_value_estimator(gamma=0.5)
    assert float(inner.value_estimator.gamma) == 0.5 and loss.value_estimator is inner.value_estimator
    updater = SoftUpdate(loss, tau=0.5)
    before = inner.target_value_network_params.clone()
    out = _call(loss, _data("DDPGLoss").set("density_ratio", torch.ones(B)))
    (out["loss_value"] + out["loss_actor"]).backward()
    torch.optim.SGD(loss.parameters(), lr=0.1).step()
    updater.step()
    after = inner.target_value_network_params
    assert any(not torch.equal(before[k], after[k]) for k in after.keys(True, True))
    assert inner.use_prioritized_weights is False  # the product ŵ·p is the wrapper's


def test_reduction_sum_and_none():
    w = torch.rand(B, generator=torch.Generator().manual_seed(7))
    td = _data("BCLoss")
    per_sample = _call(_build("BCLoss", "none"), td)["loss_bc"]  # [B, ACT]: elementwise
    summed = _call(WeightedLoss(_build("BCLoss", "none"), reduction="sum"), td.clone().set("density_ratio", w))
    torch.testing.assert_close(summed["loss_bc"], (per_sample.sum(-1) * w).sum())
    rows = _call(WeightedLoss(_build("BCLoss", "none"), reduction="none"), td.clone().set("density_ratio", w))
    torch.testing.assert_close(rows["loss_bc"], per_sample.mean(-1) * w)


def test_dtype_moves_and_modes_reach_the_wrapped_loss():
    inner = _build("IQLLoss", "none")
    inner.make_value_estimator(gamma=0.9)
    loss = WeightedLoss(inner).double()
    assert all(p.dtype == torch.float64 for p in inner.parameters())
    td = _data("IQLLoss").apply(lambda x: x.double() if x.is_floating_point() else x)
    out = _call(loss, td.set("density_ratio", torch.ones(B, dtype=torch.float64)))
    assert out["loss_qvalue"].dtype == torch.float64
    loss.eval()
    assert not inner.training
    loss.train()
    assert inner.training
    copy = WeightedLoss(_build("IQLLoss", "none"))
    copy.make_value_estimator(gamma=0.9)
    copy.load_state_dict(loss.float().state_dict())
    assert all(torch.equal(a, b) for a, b in zip(copy.parameters(), inner.parameters()))


def test_rows_masked_invalid_get_weight_zero():
    """A "shifted_valid" mask (torchrl's validity mask) weighs as 0/1 weights do."""
    keep = torch.tensor([1, 0, 1, 1, 0, 0, 1, 0], dtype=torch.bool)
    w = torch.rand(B, generator=torch.Generator().manual_seed(8)) + 0.1
    td = _data("IQLLoss")
    loss = WeightedLoss(_build("IQLLoss", "none"))
    masked = _terms(_call(loss, td.clone().set("density_ratio", w).set("shifted_valid", keep.unsqueeze(-1))))
    selected = _terms(_call(loss, td.clone().set("density_ratio", w * keep)))
    for key in selected:
        torch.testing.assert_close(masked[key], selected[key], msg=key)


def test_the_wrapped_losss_mask_key_setting_says_which_entry_masks():
    """The wrapped loss's ``loss_mask_key`` (torchrl's setting) names the mask entry read; ``None`` reads none."""
    keep = torch.tensor([1, 0, 1, 1, 0, 0, 1, 0], dtype=torch.bool)
    w = torch.rand(B, generator=torch.Generator().manual_seed(8)) + 0.1
    td = _data("IQLLoss").set("density_ratio", w).set("my_valid", keep.unsqueeze(-1))
    td.set("shifted_valid", torch.ones(B, 1, dtype=torch.bool))  # "auto" would read this one: all valid
    loss = WeightedLoss(_build("IQLLoss", "none"))
    unmasked = _terms(_call(loss, td.clone()))
    loss.loss_module.loss_mask_key = "my_valid"
    masked = _terms(_call(loss, td.clone()))
    selected = _terms(_call(loss, td.clone().set("density_ratio", w * keep)))
    loss.loss_module.loss_mask_key = None
    none = _terms(_call(loss, td.clone().set("shifted_valid", torch.zeros(B, 1, dtype=torch.bool))))
    for key in selected:
        torch.testing.assert_close(masked[key], selected[key], msg=key)
        torch.testing.assert_close(none[key], unmasked[key], msg=key)
