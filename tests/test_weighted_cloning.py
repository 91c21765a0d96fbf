"""``q.expert_bc_weighted_d``: the actor also clones the D batch, each row weighted by its stored ŵ and the term
self-normalised over the batch (:func:`~torchrl_wbrm.objectives.functional.action_cloning`, used by
:class:`~torchrl_wbrm.algos.base.ExpertCloning`)."""
from __future__ import annotations

import json

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded

from tests.references import tiny_lqr_config
from torchrl_wbrm.algos.base import ExpertCloning
from torchrl_wbrm.modules import make_deterministic_actor, make_q_network
from torchrl_wbrm.objectives import WeightedBellmanLoss
from torchrl_wbrm.objectives.functional import action_cloning
from torchrl_wbrm.training.config import WBRMConfig, validate_config

OBS, ACT = 3, 2


# ---------------------------------------------------------------- the equation
def test_action_cloning_known_answers():
    mu = torch.tensor([[1.0, 0.0], [0.0, 4.0]])
    action = torch.zeros(2, 2)
    h = torch.tensor([1.0, 2.0])
    # per row ‖(μ − a)/h‖²/m: (1 + 0)/2 = 0.5 and (0 + 4)/2 = 2
    assert action_cloning(mu, action, h).item() == pytest.approx((0.5 + 2.0) / 2)
    assert action_cloning(mu, action, h, torch.tensor([3.0, 1.0])).item() == pytest.approx((3 * 0.5 + 2.0) / 4)
    # a [B, 1] weight, as the trainer stores "density_ratio"
    assert action_cloning(mu, action, h, torch.tensor([[3.0], [1.0]])).item() == pytest.approx(0.875)


def test_a_row_of_weight_zero_drops_out():
    torch.manual_seed(0)
    mu, action = torch.randn(5, ACT, requires_grad=True), torch.randn(5, ACT)
    h = torch.tensor([0.5, 2.0])
    w = torch.tensor([1.0, 0.0, 2.0, 0.5, 0.0])
    kept = w > 0
    value = action_cloning(mu, action, h, w)
    torch.testing.assert_close(value, action_cloning(mu[kept], action[kept], h, w[kept]))
    value.backward()
    assert torch.all(mu.grad[~kept] == 0) and torch.all(mu.grad[kept].abs().sum(-1) > 0)


@pytest.mark.parametrize("c", [1.0, 0.3, 7.0])
def test_equal_weights_give_the_plain_mean(c):
    torch.manual_seed(1)
    mu, action = torch.randn(8, ACT), torch.randn(8, ACT)
    h = torch.tensor([1.0, 3.0])
    torch.testing.assert_close(action_cloning(mu, action, h, torch.full((8, 1), c)), action_cloning(mu, action, h))


def test_all_zero_weights_give_zero_and_no_gradient_reaches_the_weights():
    mu, action, h = torch.ones(4, ACT), torch.zeros(4, ACT), torch.ones(ACT)
    assert action_cloning(mu, action, h, torch.zeros(4)).item() == 0.0
    w = torch.rand(4, requires_grad=True)
    action_cloning(mu.requires_grad_(), action, h, w).backward()
    assert w.grad is None


# ---------------------------------------------------------------- in the actor step
def _parts(seed: int = 0):
    torch.manual_seed(seed)
    spec = Bounded(low=torch.tensor([-1.0, -2.0]), high=torch.tensor([1.0, 2.0]), shape=(ACT,))
    actor = make_deterministic_actor(OBS, spec, num_cells=[8])
    loss = WeightedBellmanLoss(make_q_network(OBS, ACT, num_cells=[8], initial_bias=0.0), actor_network=actor, action_spec=spec)
    loss.make_value_estimator(gamma=0.9)
    expert = TensorDict({"observation": torch.randn(16, OBS), "action": torch.rand(16, ACT) * 2 - 1}, [16])
    n = 6
    batch = TensorDict({
        "observation": torch.randn(n, OBS), "action": torch.rand(n, ACT) * 2 - 1,
        "density_ratio": torch.tensor([[2.0], [0.0], [1.0], [0.5], [0.0], [3.0]]),
        "next": {"observation": torch.randn(n, OBS), "reward": torch.randn(n, 1), "done": torch.zeros(n, 1, dtype=torch.bool),
                 "terminated": torch.zeros(n, 1, dtype=torch.bool)},
    }, [n])
    return spec, actor, loss, expert, batch


class _Fixed:
    def __init__(self, batch):
        self.batch = batch

    def sample(self):
        return self.batch


def _cloning(actor, expert, spec, **kwargs):
    cloning = ExpertCloning(actor, expert, spec, alpha=1.0, batch_size=8, **kwargs)
    cloning.buffer = _Fixed(expert[:8])  # the same S^e batch on every call
    return cloning


def test_the_weighted_term_is_added_to_the_s_e_term():
    spec, actor, loss, expert, batch = _parts()
    params = loss.actor_network_params
    q_loss, diagnostics = loss.actor_loss(batch)
    q_abs = diagnostics["actor_q_abs_mean"]
    plain, plain_figures = _cloning(actor, expert, spec)(q_loss, q_abs, params)
    weighted, figures = _cloning(actor, expert, spec, weighted_d=True)(q_loss, q_abs, params, batch)
    with params.to_module(actor):
        mu = actor(batch.select("observation").clone())["action"]
    h = (spec.space.high - spec.space.low) / 2
    w = batch["density_ratio"].squeeze(-1)
    by_hand = (w * ((mu - batch["action"]) / h).pow(2).mean(-1)).sum() / w.sum()
    torch.testing.assert_close(figures["weighted_d_bc_loss"], by_hand.detach())
    torch.testing.assert_close(weighted, plain + by_hand)
    torch.testing.assert_close(figures["expert_bc_loss"], plain_figures["expert_bc_loss"])
    assert "weighted_d_bc_loss" not in plain_figures
    with pytest.raises(ValueError, match="pass it as batch="):
        _cloning(actor, expert, spec, weighted_d=True)(q_loss, q_abs, params)


def test_the_step_weighs_the_q_term_by_the_mean_of_abs_q():
    """TD3+BC's λ = α / mean_D |Q(x, μ(x))|, not α / |mean_D Q|: a batch whose Q changes sign has a mean near 0,
    and λ would explode. The algo's step hands ExpertCloning the loss's ``"actor_q_abs_mean"``."""
    from omegaconf import OmegaConf

    from torchrl_wbrm.algos.base import bellman_step

    spec, actor, loss, expert, batch = _parts()

    def q_of_mu():
        with loss.actor_network_params.to_module(actor):
            mu = actor(batch.select("observation").clone())["action"]
        with loss.value_network_params.to_module(loss.value_network):
            return loss.value_network(batch["observation"], mu).reshape(-1).detach()

    bias = [p for name, p in loss.value_network_params.items(True, True) if name[-1] == "bias"][-1]
    with torch.no_grad():  # shift Q so that its batch mean is about 0 and its values of both signs
        bias.sub_(q_of_mu().mean() - 0.01)
    q = q_of_mu()
    assert (q > 0).any() and (q < 0).any() and q.mean().abs() < 0.1 * q.abs().mean(), q
    q_loss, diagnostics = loss.actor_loss(batch)
    torch.testing.assert_close(diagnostics["actor_q_abs_mean"], q.abs().mean())
    torch.testing.assert_close(diagnostics["actor_q_mean"], q.mean())
    seen = {}

    def spy(loss_q, q_abs_mean, params, batch=None):  # stands in for ExpertCloning: records what the step hands it
        seen["q_abs_mean"] = q_abs_mean
        return loss_q, {}

    cfg = OmegaConf.create({"q": {"grad_clip": None, "actor_delay": 1}})
    optimisers = {"value": torch.optim.SGD(loss.value_network_params.values(True, True), lr=0.0),
                  "actor": torch.optim.SGD(loss.actor_network_params.values(True, True), lr=0.0)}
    bellman_step(loss, optimisers, cfg, cloning=spy)(batch, 0)
    torch.testing.assert_close(seen["q_abs_mean"], diagnostics["actor_q_abs_mean"])


def test_gradients_reach_only_the_actor():
    spec, actor, loss, expert, batch = _parts()
    batch["density_ratio"].requires_grad_()
    q_loss, diagnostics = loss.actor_loss(batch)
    value, _ = _cloning(actor, expert, spec, weighted_d=True)(q_loss, diagnostics["actor_q_abs_mean"],
                                                               loss.actor_network_params, batch)
    value.backward()
    actor_grads = [p.grad for p in loss.actor_network_params.values(True, True) if p.requires_grad]
    assert all(g is not None for g in actor_grads) and any(g.abs().sum() > 0 for g in actor_grads)
    assert all(p.grad is None or not p.grad.any() for p in loss.value_network_params.values(True, True))
    assert batch["density_ratio"].grad is None


def test_only_the_weighted_rows_of_d_pull_the_actor():
    """Two D batches that differ only in the actions of rows of weight 0 give the same loss."""
    spec, actor, loss, expert, batch = _parts()
    other = batch.clone()
    zero = batch["density_ratio"].squeeze(-1) == 0
    other["action"][zero] = -other["action"][zero]
    cloning = _cloning(actor, expert, spec, weighted_d=True)
    q_loss, diagnostics = loss.actor_loss(batch)
    q_abs = diagnostics["actor_q_abs_mean"]
    a, _ = cloning(q_loss, q_abs, loss.actor_network_params, batch)
    b, _ = cloning(q_loss, q_abs, loss.actor_network_params, other)
    torch.testing.assert_close(a, b)


# ---------------------------------------------------------------- the config
def test_the_setting_is_off_by_default_and_checked():
    assert WBRMConfig().q.expert_bc_weighted_d is False
    cfg = tiny_lqr_config(q={"expert_bc_weighted_d": True})
    validate_config(cfg)
    validate_config(tiny_lqr_config(algo="brm", q={"expert_bc_weighted_d": True}))  # ŵ ≡ 1: plain cloning of D
    with pytest.raises(ValueError, match="q.expert_bc_alpha > 0"):
        validate_config(tiny_lqr_config(q={"expert_bc_weighted_d": True, "expert_bc_alpha": 0.0}))
    with pytest.raises(ValueError, match="not algo=bc"):
        validate_config(tiny_lqr_config(algo="bc", q={"expert_bc_weighted_d": True}))


# ---------------------------------------------------------------- the seeds in one process
def test_brm_with_weighted_d_clones_all_of_d_in_a_multi_seed_run(tmp_path):
    from torchrl_wbrm.training.seeds import run_seeds

    cfg = tiny_lqr_config(algo="brm", seeds=[0, 1], q={"expert_bc_weighted_d": True})
    results = run_seeds(cfg, tmp_path / "brm", progress=False)
    assert results["status"] == "finished"
    history = json.loads((tmp_path / "brm" / "seed0" / "history.json").read_text())
    rows = [r for r in history if r.get("stage") == "q_train" and "weighted_d_bc_loss" in r]
    assert rows and all(r["weighted_d_bc_loss"] >= 0 for r in rows)
