"""WeightedBellmanLoss follows TorchRL's per-sample weight convention (``"priority_weight"``,
``use_prioritized_weights``, reduced as ``Σ pᵢ lᵢ / Σ pᵢ``), with ŵ inside each term ``lᵢ = ŵᵢ δᵢ²``; ŵ stored as ``"priority_weight"`` weights the TorchRL losses that
read it natively (``DQNLoss`` here; which losses those are, and ``WeightedLoss`` for the others:
tests/test_weighted_loss.py)."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.modules import MLP, QValueActor
from torchrl.objectives import DQNLoss

from torchrl_wbrm.modules import make_deterministic_actor, make_q_network
from torchrl_wbrm.objectives import WeightedBellmanLoss
from torchrl_wbrm.ratio import store_density_ratio

N = 32


def _batch(seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    spec = Bounded(-1.0, 1.0, (1,))
    return TensorDict({
        "observation": torch.randn(N, 2, generator=g),
        "action": spec.low + 2 * torch.rand(N, 1, generator=g),
        "density_ratio": 2 * torch.rand(N, 1, generator=g),
        "priority_weight": torch.rand(N, generator=g),
        ("next", "observation"): torch.randn(N, 2, generator=g),
        ("next", "reward"): torch.randn(N, 1, generator=g),
        ("next", "done"): torch.zeros(N, 1, dtype=torch.bool),
        ("next", "terminated"): torch.zeros(N, 1, dtype=torch.bool),
    }, [N])


def _loss(**kwargs) -> WeightedBellmanLoss:
    torch.manual_seed(0)
    spec = Bounded(-1.0, 1.0, (1,))
    loss = WeightedBellmanLoss(make_q_network(2, 1, initial_bias=0.0, num_cells=(16,)),
                               actor_network=make_deterministic_actor(2, spec, num_cells=(16,)), **kwargs)
    loss.make_value_estimator(gamma=0.9)
    return loss


def _value(loss, batch) -> torch.Tensor:
    return loss(batch.clone())["loss_value"]


def test_priority_weight_multiplies_the_ratio():
    batch = _batch()
    both = _value(_loss(), batch)
    product = batch.exclude("priority_weight")
    product["density_ratio"] = batch["density_ratio"] * batch["priority_weight"].unsqueeze(-1)
    p = batch["priority_weight"]
    # TorchRL's rule: Σ pᵢ ŵᵢ δᵢ² / Σ pᵢ, i.e. the mean of (ŵ p) δ² rescaled by n / Σ p
    torch.testing.assert_close(both, _value(_loss(), product) * N / p.sum(), rtol=1e-5, atol=0)
    ratio_only = _value(_loss(), batch.exclude("priority_weight"))
    assert not torch.allclose(both, ratio_only)
    # by hand, with δ from the unweighted per-sample residual
    per_sample = _loss(use_weights=False, use_prioritized_weights=False, reduction="none")(batch.clone())["loss_value"]
    w = batch["density_ratio"].squeeze(-1)
    torch.testing.assert_close(both, (p * w * per_sample).sum() / p.sum(), rtol=1e-5, atol=0)


def test_use_prioritized_weights_false_ignores_it_and_auto_or_true_read_it():
    batch = _batch()
    ratio_only = _value(_loss(), batch.exclude("priority_weight"))
    torch.testing.assert_close(_value(_loss(use_prioritized_weights=False), batch), ratio_only, rtol=0, atol=0)
    torch.testing.assert_close(_value(_loss(use_prioritized_weights=True), batch), _value(_loss(), batch),
                               rtol=0, atol=0)
    # absent, "auto" and True both fall back to ŵ alone (as TorchRL's losses do)
    torch.testing.assert_close(_value(_loss(use_prioritized_weights=True), batch.exclude("priority_weight")),
                               ratio_only, rtol=0, atol=0)
    with pytest.raises(ValueError, match="use_prioritized_weights"):
        _loss(use_prioritized_weights="yes")


def test_priority_weight_alone_without_the_ratio():
    batch = _batch()
    alone = _value(_loss(use_weights=False), batch.exclude("density_ratio"))
    as_ratio = batch.exclude("priority_weight")
    as_ratio["density_ratio"] = batch["priority_weight"].unsqueeze(-1)
    torch.testing.assert_close(alone, _value(_loss(), as_ratio) * N / batch["priority_weight"].sum(), rtol=1e-5, atol=0)
    torch.testing.assert_close(alone, _value(_loss(weight_reduction="normalised"), as_ratio), rtol=1e-5, atol=0)


def test_priority_weight_key_is_configurable_and_never_counted_twice():
    batch = _batch()
    moved = batch.rename_key_("priority_weight", "importance")
    loss = _loss()
    loss.set_keys(priority_weight="importance")
    torch.testing.assert_close(_value(loss, moved), _value(_loss(), _batch()), rtol=0, atol=0)
    # ŵ itself stored as "priority_weight" and read as the weight: applied once, not squared
    same = _batch().exclude("density_ratio")
    loss = _loss()
    loss.set_keys(weight="priority_weight")
    as_ratio = same.exclude("priority_weight")
    as_ratio["density_ratio"] = same["priority_weight"].unsqueeze(-1)
    torch.testing.assert_close(_value(loss, same), _value(_loss(use_prioritized_weights=False), as_ratio),
                               rtol=0, atol=0)


def test_discrete_head_reads_the_priority_weight_too():
    torch.manual_seed(0)
    n_actions = 3
    actor = QValueActor(MLP(in_features=2, out_features=n_actions, num_cells=[16]), in_keys=["observation"],
                        spec=None, action_space="one-hot")
    batch = _batch()
    batch["action"] = torch.nn.functional.one_hot(torch.randint(n_actions, (N,)), n_actions)
    loss = WeightedBellmanLoss(actor)
    loss.make_value_estimator(gamma=0.9)
    both = loss(batch.clone())["loss_value"]
    product = batch.exclude("priority_weight")
    product["density_ratio"] = batch["density_ratio"] * batch["priority_weight"].unsqueeze(-1)
    torch.testing.assert_close(both, loss(product)["loss_value"] * N / batch["priority_weight"].sum(), rtol=1e-5, atol=0)


def test_ratio_stored_as_priority_weight_weights_torchrls_dqn_loss():
    """store_density_ratio(..., key="priority_weight") makes TorchRL's DQNLoss ŵ-weighted: its loss becomes
    Σ ŵᵢ lᵢ / Σ ŵᵢ of the unweighted per-sample losses."""
    torch.manual_seed(0)
    n_actions = 3
    actor = QValueActor(MLP(in_features=2, out_features=n_actions, num_cells=[16]), in_keys=["observation"],
                        spec=None, action_space="one-hot")
    batch = _batch().exclude("priority_weight", "density_ratio")
    batch["action"] = torch.nn.functional.one_hot(torch.randint(n_actions, (N,)), n_actions)
    w = store_density_ratio(batch, torch.rand(N) * 3, key="priority_weight")
    dqn = DQNLoss(actor, loss_function="l2", delay_value=True, action_space="one-hot")
    dqn.make_value_estimator(gamma=0.9)
    weighted = dqn(batch.clone())["loss"]
    per_sample = DQNLoss(actor, loss_function="l2", delay_value=True, action_space="one-hot", reduction="none",
                         use_prioritized_weights=False)
    per_sample.make_value_estimator(gamma=0.9)
    lossed = per_sample(batch.clone())["loss"]
    torch.testing.assert_close(weighted, (w * lossed).sum() / w.sum(), rtol=1e-5, atol=0)
