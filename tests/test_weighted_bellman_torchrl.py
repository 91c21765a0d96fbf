"""WeightedBellmanLoss against TorchRL's conventions: validity masks, priority weights, delay_value's meaning,
twin critics, vmap ensembles, torch.compile and dtype / device moves (each compared with a torchrl loss)."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, OneHot
from torchrl.objectives import DQNLoss, HardUpdate, SoftUpdate

from torchrl_wbrm.modules import make_deterministic_actor, make_discrete_q_network, make_q_network
from torchrl_wbrm.objectives import WeightedBellmanLoss, WeightedLoss

GAMMA = 0.9
SPEC = OneHot(3)


def _discrete_batch(n=16, seed=0, weight=True) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    data = TensorDict({
        "observation": torch.randn(n, 4, generator=g),
        "action": torch.nn.functional.one_hot(torch.randint(0, 3, (n,), generator=g), 3),
        ("next", "observation"): torch.randn(n, 4, generator=g),
        ("next", "reward"): torch.randn(n, 1, generator=g),
        ("next", "done"): torch.rand(n, 1, generator=g) < 0.3,
        ("next", "terminated"): torch.rand(n, 1, generator=g) < 0.2,
    }, [n])
    if weight:
        data["density_ratio"] = torch.rand(n, 1, generator=g) * 2
    return data


def _discrete_pair(**kwargs):
    """A DQNLoss (l2, target network) and a WeightedBellmanLoss on the same Q head, targets moved off the online Q."""
    torch.manual_seed(0)
    q = make_discrete_q_network(4, 3, num_cells=(16,))
    dqn = DQNLoss(q, loss_function="l2", delay_value=kwargs.get("delay_value", True), action_space=SPEC)
    ours = WeightedBellmanLoss(q, residual="squared", **kwargs)
    for loss in (dqn, ours):
        loss.make_value_estimator(gamma=GAMMA)
        if kwargs.get("delay_value", True):
            HardUpdate(loss, value_network_update_interval=10)
    with torch.no_grad():
        for p in q.parameters():
            p.add_(0.3 * torch.randn_like(p))
    return dqn, ours


# ---------------------------------------------------------------- goal: masks
@pytest.mark.parametrize("mask_key", [("collector", "mask"), "shifted_valid"])
def test_masked_rows_are_dropped_as_dqn_loss_drops_them(mask_key):
    """A validity mask on half the rows (what SliceSampler(pad_output=True) writes): the loss is DQNLoss's on the same
    masked batch, and the loss over the valid half alone; NaN padding in the masked rows changes nothing."""
    dqn, ours = _discrete_pair(use_weights=False)
    data = _discrete_batch(weight=False)
    mask = torch.arange(16) % 2 == 0
    data.set(mask_key, mask.unsqueeze(-1))
    expected = dqn(data.clone())["loss"]
    torch.testing.assert_close(ours(data.clone())["loss_value"], expected)
    torch.testing.assert_close(ours(data[mask].exclude(mask_key))["loss_value"], expected)
    assert (ours(data.exclude(mask_key))["loss_value"] - expected).abs() > 1e-3  # the mask matters here
    padded = data.clone()
    padded["next", "reward"][~mask] = float("nan")
    ours.check_inputs = False  # (the input check would name the NaN reward; padding is what masks are for)
    torch.testing.assert_close(ours(padded)["loss_value"], expected)


def test_masks_drop_weighted_rows_and_actor_rows():
    """With ŵ and an actor: the masked batch gives the valid rows' value and actor losses."""
    torch.manual_seed(0)
    spec = Bounded(-1.0, 1.0, (1,))
    loss = WeightedBellmanLoss(make_q_network(2, 1, num_cells=(8,), initial_bias=0.0),
                               actor_network=make_deterministic_actor(2, spec, num_cells=(8,)))
    loss.make_value_estimator(gamma=GAMMA)
    n = 12
    data = TensorDict({
        "observation": torch.randn(n, 2), "action": spec.rand((n,)), "density_ratio": torch.rand(n, 1) * 2,
        ("next", "observation"): torch.randn(n, 2), ("next", "reward"): torch.randn(n, 1),
        ("next", "done"): torch.zeros(n, 1, dtype=torch.bool), ("next", "terminated"): torch.zeros(n, 1, dtype=torch.bool),
    }, [n])
    mask = torch.rand(n) < 0.5
    mask[0] = True
    masked = loss(data.clone().set(("collector", "mask"), mask.unsqueeze(-1)))
    alone = loss(data[mask])
    for key in ("loss_value", "loss_actor", "td_error_mean", "q_mean", "weight_ess"):
        torch.testing.assert_close(masked[key], alone[key])


# ---------------------------------------------------------------- goal: TorchRL's meanings
def test_priority_weight_reduces_as_torchrl_does():
    """A priority weight p: Σ pᵢ lᵢ / Σ pᵢ, DQNLoss's value, also for the unweighted-ŵ loss and for WeightedLoss(DQNLoss)
    given p as its weight; with ŵ the paper's mean form multiplies it into each term: Σ pᵢ ŵᵢ lᵢ / Σ pᵢ."""
    dqn, ours = _discrete_pair(use_weights=False)
    data = _discrete_batch()
    data["priority_weight"] = torch.rand(16) * 3
    expected = dqn(data.clone())["loss"]
    torch.testing.assert_close(ours(data.clone())["loss_value"], expected)
    wrapped = WeightedLoss(DQNLoss(dqn.value_network, loss_function="l2", action_space=SPEC), weight_key="p")
    wrapped.loss_module.make_value_estimator(gamma=GAMMA)
    wrapped.loss_module.target_value_network_params.update_(dqn.target_value_network_params)
    torch.testing.assert_close(wrapped(data.clone().set("p", data["priority_weight"]).exclude("priority_weight"))["loss"],
                               expected)
    # ŵ and p together
    dqn_none = DQNLoss(dqn.value_network, loss_function="l2", action_space=SPEC, reduction="none")
    dqn_none.make_value_estimator(gamma=GAMMA)
    dqn_none.target_value_network_params.update_(dqn.target_value_network_params)
    per_sample = dqn_none(data.exclude("priority_weight"))["loss"]
    w, p = data["density_ratio"].squeeze(-1), data["priority_weight"]
    _, weighted = _discrete_pair()
    torch.testing.assert_close(weighted(data.clone())["loss_value"], (p * w * per_sample).sum() / p.sum())
    # the self-normalised choice: Σ ŵᵢ pᵢ lᵢ / Σ ŵᵢ pᵢ, WeightedLoss(DQNLoss)'s value
    _, normalised = _discrete_pair(weight_reduction="normalised")
    torch.testing.assert_close(normalised(data.clone())["loss_value"], (p * w * per_sample).sum() / (p * w).sum())
    torch.testing.assert_close(wrapped(data.clone().set("p", w * p).exclude("priority_weight"))["loss"],
                               (p * w * per_sample).sum() / (p * w).sum())


def test_delay_value_false_is_torchrl_semi_gradient():
    """delay_value=False bootstraps on the online Q, detached: DQNLoss(delay_value=False)'s value and gradient;
    residual_gradient=True keeps the value and adds the gradient through max Q(x', ·)."""
    dqn, ours = _discrete_pair(delay_value=False, use_weights=False)
    data = _discrete_batch(weight=False)
    loss_dqn, loss_ours = dqn(data.clone())["loss"], ours(data.clone())["loss_value"]
    torch.testing.assert_close(loss_ours, loss_dqn)
    params = list(dqn.value_network_params.values(True, True))
    grads_dqn = torch.autograd.grad(loss_dqn, params)
    grads_ours = torch.autograd.grad(loss_ours, list(ours.value_network_params.values(True, True)))
    for a, b in zip(grads_dqn, grads_ours):
        torch.testing.assert_close(a, b)
    _, residual = _discrete_pair(delay_value=False, residual_gradient=True, use_weights=False)
    loss_rg = residual(data.clone())["loss_value"]
    torch.testing.assert_close(loss_rg, loss_dqn)
    grads_rg = torch.autograd.grad(loss_rg, list(residual.value_network_params.values(True, True)))
    assert max((a - b).abs().max() for a, b in zip(grads_rg, grads_dqn)) > 1e-3
    with pytest.raises(ValueError, match="residual_gradient=True .* needs delay_value=False"):
        WeightedBellmanLoss(make_discrete_q_network(4, 3, num_cells=(8,)), residual_gradient=True)


def test_vmap_randomness_is_different_when_the_maximiser_samples():
    spec = Bounded(-1.0, 1.0, (1,))
    q = make_q_network(2, 1, num_cells=(8,), initial_bias=0.0)
    assert WeightedBellmanLoss(q, maximiser="sampled", action_spec=spec).vmap_randomness == "different"
    actor = make_deterministic_actor(2, spec, num_cells=(8,))
    assert WeightedBellmanLoss(q, actor_network=actor).vmap_randomness == "error"
    assert WeightedBellmanLoss(q, actor_network=actor, policy_noise=0.2).vmap_randomness == "different"


# ---------------------------------------------------------------- goal: vmap ensembles and compile
def _continuous_batch(seed: int, n: int = 8) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    return TensorDict({
        "observation": torch.randn(n, 2, generator=g), "action": torch.rand(n, 1, generator=g) * 2 - 1,
        "density_ratio": torch.rand(n, 1, generator=g) * 2,
        ("next", "observation"): torch.randn(n, 2, generator=g), ("next", "reward"): torch.randn(n, 1, generator=g),
        ("next", "done"): torch.zeros(n, 1, dtype=torch.bool),
        ("next", "terminated"): torch.rand(n, 1, generator=g) < 0.2,
    }, [n])


def _continuous_loss(**kwargs) -> WeightedBellmanLoss:
    torch.manual_seed(0)
    spec = Bounded(-1.0, 1.0, (1,))
    loss = WeightedBellmanLoss(make_q_network(2, 1, num_cells=(8,), initial_bias=0.0),
                               actor_network=make_deterministic_actor(2, spec, num_cells=(8,)), **kwargs)
    loss.make_value_estimator(gamma=GAMMA)
    SoftUpdate(loss, tau=0.1)
    return loss


def _members(loss, num_members: int) -> TensorDict:
    """The loss's parameters, stacked for ``num_members`` members, each perturbed with its own generator."""
    params = TensorDict.from_module(loss)
    members = []
    for m in range(num_members):
        g = torch.Generator().manual_seed(100 + m)
        members.append(params.apply(lambda p: p + 0.1 * torch.randn(p.shape, generator=g)
                                    if p.is_floating_point() and p.device.type != "meta" else p))
    return torch.stack(members).detach()


def _member_loss(seed: int, **kwargs) -> WeightedBellmanLoss:
    """A loss of its own, with networks drawn from ``seed`` and targets moved off them."""
    torch.manual_seed(seed)
    spec = Bounded(-1.0, 1.0, (1,))
    loss = WeightedBellmanLoss(make_q_network(2, 1, num_cells=(8,), initial_bias=0.0),
                               actor_network=make_deterministic_actor(2, spec, num_cells=(8,)), **kwargs)
    loss.make_value_estimator(gamma=GAMMA)
    SoftUpdate(loss, tau=0.1)
    with torch.no_grad():
        for params in (loss.target_value_network_params, loss.target_actor_network_params):
            for p in params.values(True, True):
                p.add_(0.1 * torch.randn_like(p))
    return loss


def _own_losses_and_gradients(loss, batch) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """``(loss_value, loss_actor, {(params name, *key): gradient of their sum})`` of a loss called on its own."""
    loss.zero_grad()
    out = loss(batch)
    (out["loss_value"] + out["loss_actor"]).backward()
    grads = {(name, *key): p.grad for name in ("value_network_params", "actor_network_params")
             for key, p in getattr(loss, name).items(True, True)}
    return out["loss_value"].detach(), out["loss_actor"].detach(), grads


def _assert_member_equals_its_own_loss(grad_of, value, actor, own_loss, batch) -> None:
    """A member's losses and the gradients they put on its parameters (``grad_of(key)``) are those of its own loss
    object."""
    own_value, own_actor, own_grads = _own_losses_and_gradients(own_loss, batch)
    torch.testing.assert_close((value, actor), (own_value, own_actor))
    for key, grad in own_grads.items():
        if grad is not None:  # (not the actor's action bounds: buffers)
            member_grad = grad_of(key)
            assert member_grad is not None, key
            torch.testing.assert_close(member_grad, grad, msg=lambda msg: f"{key}: {msg}")


def _stacked(losses) -> TensorDict:
    """TorchRL's ensemble parameters: ``TensorDict.from_modules`` of the members' losses, as leaf tensors."""
    return TensorDict.from_modules(*losses).apply(lambda t: t.detach().clone().requires_grad_(t.is_floating_point()))


@pytest.mark.parametrize("batch_per_member, fast_path, kwargs", [
    (False, True, {}), (True, True, {}), (False, False, {}), (True, False, {}), (True, True, {"num_qvalue_nets": 2}),
])
def test_a_stacked_parameter_ensemble_under_vmap_equals_each_members_own_loss(batch_per_member, fast_path, kwargs):
    """TorchRL's ensemble recipe (TensorDict.from_modules of 3 members' losses, params.to_module inside torch.vmap on
    a fourth loss, with its own parameters): every member's losses and gradients equal those of the member's own
    loss object called directly, with one batch for all members and with one batch per member, on the tensor path
    and the TensorDict path, with one critic and with twin critics."""
    num_members = 3
    members = [_member_loss(100 + m, **kwargs) for m in range(num_members)]
    host = _member_loss(0, **kwargs)
    host.fast_path = fast_path
    for i in range(3):
        stacked = _stacked(members)

        def call(params, batch):
            with params.to_module(host):
                out = host(batch)
            return out["loss_value"], out["loss_actor"]

        batches = [_continuous_batch(1000 * i + m) for m in range(num_members if batch_per_member else 1)]
        batch = torch.stack(batches) if batch_per_member else batches[0]
        value, actor = torch.vmap(call, (0, 0 if batch_per_member else None),
                                  randomness=host.vmap_randomness)(stacked, batch.clone())
        (value.sum() + actor.sum()).backward()
        for m in range(num_members):
            def grad_of(key, m=m):
                grad = stacked[key].grad
                return None if grad is None else grad[m]

            _assert_member_equals_its_own_loss(grad_of, value[m], actor[m], members[m],
                                               batches[m if batch_per_member else 0].clone())


def test_the_per_sample_weight_is_checked_where_it_can_be_read_back():
    """``per_sample_weight`` (every loss's one reader of ŵ and p) refuses a negative weight outside a transform and on
    a batch a ``torch.vmap`` over other arguments shares; on a batch the vmap maps it cannot read the weight back, so
    it returns it unchecked instead of failing on the read."""
    from torchrl_wbrm.objectives.functional import per_sample_weight

    bad = TensorDict({"density_ratio": torch.tensor([1.0, -1.0])}, [2])
    with pytest.raises(ValueError, match=r"'density_ratio'"):
        per_sample_weight(bad, "density_ratio")
    with pytest.raises(ValueError, match=r"'density_ratio'"):
        torch.vmap(lambda scale, td: per_sample_weight(td, "density_ratio") * scale, (0, None))(torch.ones(3), bad)
    mapped = torch.vmap(lambda td: per_sample_weight(td, "density_ratio"))(torch.stack([bad, bad]))
    assert torch.equal(mapped, torch.tensor([[1.0, -1.0], [1.0, -1.0]]))


@pytest.mark.parametrize("fast_path", [True, False])
def test_a_batch_shared_by_a_vmap_ensemble_is_checked_and_a_batched_one_is_not_read_back(fast_path):
    """Inside ``torch.vmap`` over the parameters only (TorchRL's ensemble idiom) the batch is a plain tensor: its
    value checks run, so a NaN reward is refused by name as outside vmap. A batch mapped by vmap cannot be read back:
    its value checks are skipped and the loss is computed (the NaN reaches the loss, as with ``check_inputs=False``)."""
    members = [_member_loss(100 + m) for m in range(2)]
    host = _member_loss(0)
    host.fast_path = fast_path

    def call(params, batch):
        with params.to_module(host):
            return host(batch)["loss_value"]

    bad = _continuous_batch(3)
    bad["next", "reward"][2] = float("nan")
    with pytest.raises(ValueError, match=r"^Entry \('next', 'reward'\) .*finite"):
        torch.vmap(call, (0, None), randomness=host.vmap_randomness)(_stacked(members), bad.clone())
    value = torch.vmap(call, (0, 0), randomness=host.vmap_randomness)(_stacked(members), torch.stack([bad, bad]))
    assert value.shape == (2,) and torch.isnan(value).all()


@pytest.mark.parametrize("kwargs", [{}, {"num_qvalue_nets": 2}])
@pytest.mark.parametrize("fast_path", [True, False])
def test_params_to_module_without_vmap_computes_with_the_installed_parameters(fast_path, kwargs):
    """``with params.to_module(loss): loss(batch)`` with another loss's parameters (TensorDict.from_module) gives that
    loss's values and gradients, not those of the parameters the loss holds; the loss's own are back afterwards."""
    host, other = _member_loss(0, **kwargs), _member_loss(1, **kwargs)
    host.fast_path = fast_path
    batch = _continuous_batch(3)
    own_value, own_actor, _ = _own_losses_and_gradients(host, batch.clone())
    params = TensorDict.from_module(other).apply(lambda t: t.detach().clone().requires_grad_(t.is_floating_point()))
    host.zero_grad()
    with params.to_module(host):
        out = host(batch.clone())
    (out["loss_value"] + out["loss_actor"]).backward()
    _assert_member_equals_its_own_loss(lambda key: params[key].grad, out["loss_value"].detach(), out["loss_actor"].detach(), other,
                                       batch.clone())
    assert all(p.grad is None for p in host.parameters())
    torch.testing.assert_close(_own_losses_and_gradients(host, batch.clone())[:2], (own_value, own_actor))


def test_a_sampled_maximiser_runs_in_a_vmap_ensemble():
    loss = WeightedBellmanLoss(make_q_network(2, 1, num_cells=(8,), initial_bias=0.0), maximiser="sampled",
                               action_spec=Bounded(-1.0, 1.0, (1,)), num_action_samples=4)
    stacked = _members(loss, 2)

    def call(params, batch):
        with params.to_module(loss):
            return loss(batch)["loss_value"]

    value = torch.vmap(call, (0, None), randomness=loss.vmap_randomness)(stacked, _continuous_batch(0))
    assert value.shape == (2,) and torch.isfinite(value).all()


def _update(loss, keys):
    optimiser = torch.optim.SGD(loss.parameters(), lr=1e-2)

    def update(batch):
        out = loss(batch)
        total = sum(out[key] for key in keys)
        total.backward()
        optimiser.step()
        optimiser.zero_grad()
        return total.detach()

    return update


@pytest.mark.slow
def test_one_update_breaks_the_graph_no_more_than_dqn_loss_and_compiles_to_the_eager_values():
    """torch._dynamo.explain of one update (forward, backward, step): at most DQNLoss's graph breaks + 2 (measured:
    both 2, the backward's); the compiled loss gives the eager values."""
    dqn, _ = _discrete_pair()
    torch._dynamo.reset()
    dqn_breaks = torch._dynamo.explain(_update(dqn, ["loss"]))(_discrete_batch()).graph_break_count
    loss = _continuous_loss()
    torch._dynamo.reset()
    ours_breaks = torch._dynamo.explain(_update(loss, ["loss_value", "loss_actor"]))(
        _continuous_batch(0)).graph_break_count
    assert ours_breaks <= dqn_breaks + 2, (ours_breaks, dqn_breaks)
    loss = _continuous_loss()
    torch._dynamo.reset()
    compiled = torch.compile(lambda batch: loss(batch).select("loss_value", "loss_actor", "q_mean"), backend="aot_eager")
    for seed in range(2):
        batch = _continuous_batch(seed)
        torch.testing.assert_close(compiled(batch.clone()).to_dict(),
                                   loss(batch.clone()).select("loss_value", "loss_actor", "q_mean").to_dict())


# ---------------------------------------------------------------- goal: dtype and device moves
def _ratio_loss_and_batch():
    from torchrl_wbrm.modules import DensityRatioNetwork
    from torchrl_wbrm.objectives import RobustDensityRatioLoss

    torch.manual_seed(0)
    loss = RobustDensityRatioLoss(DensityRatioNetwork(2, 1, bounds=(0.01, 100.0), num_cells=(8,)))
    g = torch.Generator().manual_seed(0)
    batch = TensorDict({
        "behaviour": TensorDict({"observation": torch.randn(8, 2, generator=g), "action": torch.randn(8, 1, generator=g)}, [8]),
        "expert": TensorDict({"observation": torch.randn(6, 2, generator=g), "action": torch.randn(6, 1, generator=g)}, [6]),
    }, [])
    return loss, batch


def _moved_losses_agree(loss, batch, keys, move, cast):
    before = loss(batch.clone())
    moved = move(loss)
    after = moved(cast(batch.clone()))
    reference = cast(before.select(*keys))
    for key in keys:
        assert after[key].dtype == reference[key].dtype and after[key].device == reference[key].device
        torch.testing.assert_close(after[key].to(before[key]), before[key], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("which", ["bellman", "ratio"])
def test_double_after_a_forward_clears_every_cache(which):
    """``loss.double()`` after a first forward, then a float64 batch: the same losses, in float64 (a cache of the
    network's dtype was once kept past the move)."""
    if which == "bellman":
        loss, batch, keys = _continuous_loss(), _continuous_batch(0), ["loss_value", "loss_actor"]
    else:
        (loss, batch), keys = _ratio_loss_and_batch(), ["loss_density_ratio"]
    loss(batch.clone())
    assert any(k.startswith("_cache_") for k in loss.__dict__)
    _moved_losses_agree(loss, batch, keys, lambda m: m.double(),
                        lambda t: t.apply(lambda x: x.double() if x.is_floating_point() else x))
    assert loss.float()(batch.clone())[keys[0]].dtype == torch.float32


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("which", ["bellman", "ratio"])
def test_to_device_after_a_forward_clears_every_cache(which):
    if which == "bellman":
        loss, batch, keys = _continuous_loss(), _continuous_batch(0), ["loss_value", "loss_actor"]
    else:
        (loss, batch), keys = _ratio_loss_and_batch(), ["loss_density_ratio"]
    loss(batch.clone())
    _moved_losses_agree(loss, batch, keys, lambda m: m.to("cuda"), lambda t: t.to("cuda"))


# ---------------------------------------------------------------- goal: twin critics
def test_twin_critics_and_target_smoothing_give_td3_loss_critic_target():
    """num_qvalue_nets=2 and policy_noise: on the same networks and parameters, with the same seed, the Bellman
    target is TorchRL TD3Loss's (min over the target critics of Q(x', clamp(μ'(x') + clipped noise))), and the value
    and actor losses are TD3Loss's (l2)."""
    from torchrl.objectives import TD3Loss

    spec = Bounded(-1.0, 1.0, (1,))
    torch.manual_seed(0)
    q = make_q_network(2, 1, num_cells=(8,), initial_bias=0.0)
    actor = make_deterministic_actor(2, spec, num_cells=(8,))
    td3 = TD3Loss(actor, q, action_spec=spec, num_qvalue_nets=2, policy_noise=0.2, noise_clip=0.5, loss_function="l2")
    ours = WeightedBellmanLoss(q, actor_network=actor, num_qvalue_nets=2, policy_noise=0.2, noise_clip=0.5,
                               action_spec=spec, use_weights=False)
    for loss in (td3, ours):
        loss.make_value_estimator(gamma=GAMMA)
    first, second = (ours.value_network_params[i]["module", "0", "weight"] for i in (0, 1))
    assert (first - second).abs().max() > 1e-3  # two critics, initialised apart
    with torch.no_grad():
        for p in td3.target_qvalue_network_params.values(True, True):
            p.add_(0.2 * torch.randn_like(p))
    pairs = (("value_network_params", "qvalue_network_params"),
             ("target_value_network_params", "target_qvalue_network_params"),
             ("actor_network_params", "actor_network_params"),
             ("target_actor_network_params", "target_actor_network_params"))
    for name_ours, name_td3 in pairs:
        getattr(ours, name_ours).data.update_(getattr(td3, name_td3).data)
    data = _continuous_batch(0).exclude("density_ratio")
    torch.manual_seed(5)
    loss_td3, metadata = td3.value_loss(data.clone())
    torch.manual_seed(5)
    q_value, target = ours.bellman_error(data.clone())
    assert q_value.shape == (2, 8)
    torch.testing.assert_close(target, metadata["target_value"])
    torch.manual_seed(5)
    out = ours(data.clone())
    torch.testing.assert_close(out["loss_value"], loss_td3)
    torch.testing.assert_close(out["loss_actor"], td3.actor_loss(data.clone())[0])
    torch.manual_seed(5)
    unsmoothed = WeightedBellmanLoss(q, actor_network=actor, num_qvalue_nets=2, action_spec=spec, use_weights=False)
    unsmoothed.make_value_estimator(gamma=GAMMA)
    for name_ours, name_td3 in pairs:
        getattr(unsmoothed, name_ours).data.update_(getattr(td3, name_td3).data)
    assert (unsmoothed.bellman_error(data.clone())[1] - target).abs().max() > 1e-4  # the noise matters here


@pytest.mark.parametrize("index_actions", [False, True])
def test_twin_discrete_critics_bootstrap_on_the_max_of_the_minimum(index_actions):
    """A Q head with num_qvalue_nets=2: Q(x, a) per critic at the data's action (one-hot or index), and the target
    r + γ (1 − terminated) max_a min_k Q'_k(x', a); the loss sums the critics' terms."""
    torch.manual_seed(0)
    loss = WeightedBellmanLoss(make_discrete_q_network(4, 3, num_cells=(8,)), num_qvalue_nets=2, use_weights=False)
    loss.make_value_estimator(gamma=GAMMA)
    with torch.no_grad():
        for p in loss.target_value_network_params.values(True, True):
            p.add_(0.3 * torch.randn_like(p))
    data = _discrete_batch(weight=False)
    if index_actions:
        data["action"] = data["action"].argmax(-1)

    def head(params, observation):
        with params.to_module(loss.value_network):
            return loss.value_network(TensorDict({"observation": observation}, observation.shape[:1]))["action_value"]

    online = torch.stack([head(loss.value_network_params[k], data["observation"]) for k in range(2)])
    target = torch.stack([head(loss.target_value_network_params[k], data["next", "observation"]) for k in range(2)])
    action = data["action"] if not index_actions else torch.nn.functional.one_hot(data["action"], 3)
    expected_q = (online * action).sum(-1)
    not_terminated = (~data["next", "terminated"]).float().squeeze(-1)
    expected_y = data["next", "reward"].squeeze(-1) + GAMMA * not_terminated * target.amin(0).amax(-1)
    q_value, y = loss.bellman_error(data.clone())
    torch.testing.assert_close(q_value, expected_q)
    torch.testing.assert_close(y, expected_y)
    torch.testing.assert_close(loss(data.clone())["loss_value"], (expected_q - expected_y).pow(2).sum(0).mean())


@pytest.mark.parametrize("mask_key", [("collector", "mask"), "shifted_valid"])
def test_ratio_loss_drops_masked_samples(mask_key):
    """RobustDensityRatioLoss: a validity mask in the "behaviour" or "expert" samples drops those rows from every
    mean: the loss and its figures are those of the valid rows alone."""
    loss, batch = _ratio_loss_and_batch()
    loss.normalisation_coefficient = 0.5
    b_mask, e_mask = torch.tensor([1, 0, 1, 1, 0, 1, 1, 0], dtype=torch.bool), torch.tensor([1, 1, 0, 1, 0, 1]).bool()
    masked = batch.clone()
    masked["behaviour"].set(mask_key, b_mask.unsqueeze(-1))
    masked["expert"].set(mask_key, e_mask)
    alone = TensorDict({"behaviour": batch["behaviour"][b_mask], "expert": batch["expert"][e_mask]}, [])
    got, want = loss(masked), loss(alone)
    for key in want.keys():
        torch.testing.assert_close(got[key], want[key])
    assert (loss(batch)["loss_density_ratio"] - want["loss_density_ratio"]).abs() > 1e-4  # the mask matters here
