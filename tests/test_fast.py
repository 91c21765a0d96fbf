"""torchrl_wbrm.objectives._fast and torchrl_wbrm.data.sampling: the hot-path shortcuts compute exactly what the
TensorDict paths compute (no timings are asserted here; the figures are printed by benchmarks/)."""
from __future__ import annotations

import copy

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded
from torchrl.objectives import SoftUpdate

from torchrl_wbrm.data import make_replay_buffer
from torchrl_wbrm.modules import DensityRatioNetwork, make_deterministic_actor, make_q_network
from torchrl_wbrm.objectives import FQELoss, MABOLoss, RobustDensityRatioLoss, WeightedBellmanLoss
from torchrl_wbrm.objectives._fast import ForeachSoftUpdate, NetworkCall
from torchrl_wbrm.algos import adam_options
from torchrl_wbrm.algos.base import ExpertCloning
from torchrl_wbrm.data.sampling import BufferBatches, PairedSampler

SPEC = Bounded(-2.0, 2.0, (2,))


def _data(n=64, seed=0, terminated=True):
    g = torch.Generator().manual_seed(seed)
    term = torch.rand(n, 1, generator=g) < 0.2 if terminated else torch.zeros(n, 1, dtype=torch.bool)
    return TensorDict(
        {
            "observation": torch.randn(n, 3, generator=g),
            "action": 2 * torch.rand(n, 2, generator=g) - 1,
            "density_ratio": torch.rand(n, 1, generator=g) + 0.1,
            "episode": torch.arange(n),
            "next": {"observation": torch.randn(n, 3, generator=g), "reward": torch.randn(n, 1, generator=g),
                     "done": term.clone(), "terminated": term},
        },
        [n],
    )


def _pair(**kwargs):
    torch.manual_seed(0)
    q = make_q_network(3, 2, initial_bias=0.0, num_cells=(16, 16), activation="SiLU")
    actor = make_deterministic_actor(3, SPEC, num_cells=(16,))
    fast = WeightedBellmanLoss(q, actor_network=actor, **kwargs)
    fast.make_value_estimator(gamma=0.9)
    slow = copy.deepcopy(fast)
    slow.fast_path = False
    return fast, slow


def _grads(loss):
    return {k: (None if p.grad is None else p.grad.clone()) for k, p in loss.named_parameters()}


@pytest.mark.parametrize("kwargs", [
    {}, {"delay_value": False, "delay_actor": False}, {"residual": "absolute_mean"}, {"maximiser": "sampled", "num_action_samples": 8},
    {"bc_alpha": 2.5, "weight_actor_loss": True}, {"use_weights": False},
])
def test_weighted_bellman_fast_path_equals_the_tensordict_path(kwargs):
    fast, slow = _pair(**kwargs)
    for name in ("value_network", "actor_network"):
        assert fast._network_call(name).direct and not slow._network_call(name).direct
    if fast.delay_value:
        for loss in (fast, slow):
            SoftUpdate(loss, tau=0.1)
        with torch.no_grad():  # targets that differ from the online networks
            for a, b in zip(fast.target_value_network_params.values(True, True),
                            slow.target_value_network_params.values(True, True)):
                a.add_(0.1), b.add_(0.1)
    data = _data()
    outs = {}
    for name, loss in (("fast", fast), ("slow", slow)):
        torch.manual_seed(1)  # the sampled maximiser draws
        out = loss(data.clone())
        (out["loss_value"] + out["loss_actor"]).backward()
        outs[name] = (out, _grads(loss))
    (out_f, g_f), (out_s, g_s) = outs["fast"], outs["slow"]
    assert set(out_f.keys()) == set(out_s.keys())
    for key in out_f.keys():
        assert torch.equal(out_f[key], out_s[key]), key
    for key in g_f:
        assert (g_f[key] is None) == (g_s[key] is None), key
        if g_f[key] is not None:
            assert torch.equal(g_f[key], g_s[key]), key


def test_value_loss_input_checks_in_one_reduction_raise_what_the_separate_checks_raise():
    from torchrl_wbrm.objectives import NonFiniteError

    fast, _ = _pair()
    data = _data()
    data["density_ratio"][0] = -1.0
    data["observation"][3] = float("nan")
    with pytest.raises(ValueError, match=r"Entry 'density_ratio' must be finite and non-negative"):  # ŵ first, as before
        fast.value_loss(data)
    data = _data()
    data["next", "observation"][5, 1] = float("inf")
    with pytest.raises(NonFiniteError, match=r"Entry \('next', 'observation'\) holds 1 non-finite"):
        fast.value_loss(data)
    data = _data()
    data["next", "reward"].fill_(3e38)  # finite entries whose sum overflows: accepted
    loss, _ = fast.value_loss(data)
    assert loss.shape == ()


def test_actor_loss_fast_path_leaves_q_without_gradient():
    fast, _ = _pair()
    loss_actor, _ = fast.actor_loss(_data())
    loss_actor.backward()
    assert all(p.grad is None for p in fast.value_network_params.values(True, True))
    assert any(p.grad is not None for p in fast.actor_network_params.values(True, True))


def test_fast_path_is_skipped_for_networks_it_cannot_call_on_tensors():
    q = make_q_network(3, 2, initial_bias=0.0, num_cells=(8,))
    safe_actor = make_deterministic_actor(3, SPEC, num_cells=(8,))
    safe_actor.safe = True
    loss = WeightedBellmanLoss(q, actor_network=safe_actor)
    assert loss._network_call("value_network").direct and not loss._network_call("actor_network").direct
    hooked = make_q_network(3, 2, initial_bias=0.0, num_cells=(8,))
    hooked.register_forward_hook(lambda *args: None)
    hooked_loss = WeightedBellmanLoss(hooked, action_spec=SPEC)
    assert not NetworkCall(hooked, hooked_loss.value_network_params, "state_action_value").direct
    data = _data()
    out = loss(data)  # the TensorDict call for the safe actor, the tensor call for Q: one loss
    assert torch.isfinite(out["loss_value"]) and torch.isfinite(out["loss_actor"])


def test_fast_call_restores_the_meta_module_even_on_error():
    fast, _ = _pair()
    net = fast.value_network
    before = {n: p for n, p in net.named_parameters()}
    with pytest.raises(RuntimeError):  # wrong width
        fast._network_call("value_network")(fast.value_network_params,
                                            {"observation": torch.zeros(4, 1), "action": torch.zeros(4, 1)}, (4,))
    after = dict(net.named_parameters())
    assert after.keys() == before.keys() and all(after[n] is before[n] for n in before)


@pytest.mark.parametrize("kwargs", [{}, {"normalisation_coefficient": 1.0, "non_negative_correction": 0.2},
                                    {"alpha": "kl"}])
def test_ratio_fast_path_equals_the_tensordict_path(kwargs):
    torch.manual_seed(0)
    fast = RobustDensityRatioLoss(DensityRatioNetwork(3, 2, num_cells=(16,)), **kwargs)
    slow = copy.deepcopy(fast)
    slow.fast_path = False
    assert fast._network_call().direct and not slow._network_call().direct
    d = _data(32)
    batch = TensorDict({"behaviour": d.select("observation", "action"),
                        "expert": _data(16, seed=1).select("observation", "action")}, [])
    outs = []
    for loss in (fast, slow):
        out = loss(batch)
        out["loss_density_ratio"].backward()
        outs.append((out, _grads(loss)))
    for key in outs[0][0].keys():
        assert torch.equal(outs[0][0][key], outs[1][0][key]), key
    for key, grad in outs[0][1].items():
        assert torch.equal(grad, outs[1][1][key]), key


def _fqe(seed):
    torch.manual_seed(seed)
    loss = FQELoss(make_q_network(3, 2, initial_bias=0.0, num_cells=(8,)), make_deterministic_actor(3, SPEC, num_cells=(8,)))
    loss.make_value_estimator(gamma=0.9)
    SoftUpdate(loss, tau=0.1)
    data = _data(16)
    return loss, lambda: {"loss_value": loss(data.clone())["loss_value"]}


def _ratio(seed):
    torch.manual_seed(seed)
    loss = RobustDensityRatioLoss(DensityRatioNetwork(3, 2, num_cells=(8,)))
    batch = TensorDict({"behaviour": _data(16).select("observation", "action"),
                        "expert": _data(8, seed=1).select("observation", "action")}, [])
    return loss, lambda: {"loss_density_ratio": loss(batch)["loss_density_ratio"]}


def _mabo(seed):
    torch.manual_seed(seed)
    loss = MABOLoss(make_q_network(3, 2, initial_bias=0.0, num_cells=(8,)),
                    make_q_network(3, 2, initial_bias=0.0, num_cells=(8,), out_key="adversary_output"),
                    actor_network=make_deterministic_actor(3, SPEC, num_cells=(8,)), delay_value=True,
                    delay_actor=True)  # (torchrl hands out `.data` for absent targets: refused under vmap)
    loss.make_value_estimator(gamma=0.9)
    SoftUpdate(loss, tau=0.1)
    data = _data(16)

    def losses():
        out = loss(data.clone())
        return {key: out[key] for key in out.keys() if key.startswith("loss_")}

    return loss, losses


def _cloning(seed):
    torch.manual_seed(seed)
    loss = WeightedBellmanLoss(make_q_network(3, 2, initial_bias=0.0, num_cells=(8,)),
                               actor_network=make_deterministic_actor(3, SPEC, num_cells=(8,)))
    cloning = ExpertCloning(loss.actor_network, _data(32, seed=2).select("observation", "action"), SPEC, alpha=1.0,
                            batch_size=8, weighted_d=True)
    data = _data(16)

    def losses():
        torch.manual_seed(5)  # the same S^e draws
        out, _ = cloning(torch.tensor(1.0), torch.tensor(2.0), loss.actor_network_params, data)
        return {"loss_actor": out}

    return loss, losses


def _as_leaves(params: TensorDict) -> TensorDict:
    return params.apply(lambda t: t.detach().clone().requires_grad_(t.is_floating_point()))


@pytest.mark.parametrize("build", [_fqe, _ratio, _mabo, _cloning])
def test_every_network_call_reads_the_parameters_put_in_by_to_module(build):
    """Each loss that calls its networks through NetworkCall, under ``params.to_module(loss)`` with another loss's
    parameters (and, but for ExpertCloning's buffer draws, under torch.vmap over two members' stacked parameters):
    the values and gradients are those of the other loss object called on its own."""
    host, host_losses = build(0)
    members = [build(1), build(2)]
    before = {k: v.detach() for k, v in host_losses().items()}

    def own(loss, losses):
        loss.zero_grad()
        out = losses()
        sum(out.values()).backward()
        grads = {key: p.grad for key, p in TensorDict.from_module(loss).items(True, True) if p.grad is not None}
        assert grads
        return {k: v.detach() for k, v in out.items()}, grads

    def assert_member(values, grad_of, member):
        own_values, own_grads = own(*member)
        torch.testing.assert_close(values, own_values)
        assert all(not torch.equal(values[k], before[k]) for k in before)  # (not the host's own values)
        for key, grad in own_grads.items():
            torch.testing.assert_close(grad_of(key), grad, msg=lambda msg: f"{key}: {msg}")

    params = _as_leaves(TensorDict.from_module(members[0][0]))
    with params.to_module(host):
        out = host_losses()
    sum(out.values()).backward()
    assert_member({k: v.detach() for k, v in out.items()}, lambda key: params[key].grad, members[0])
    if build is _cloning:
        return
    stacked = _as_leaves(TensorDict.from_modules(*(loss for loss, _ in members)))

    def call(p):
        with p.to_module(host):
            return host_losses()

    out = torch.vmap(call, randomness="different")(stacked)
    sum(v.sum() for v in out.values()).backward()
    for m, member in enumerate(members):
        assert_member({k: v[m].detach() for k, v in out.items()}, lambda key, m=m: stacked[key].grad[m], member)


def test_foreach_soft_update_is_bitwise_torchrl_soft_update():
    a, _ = _pair()
    b = copy.deepcopy(a)
    ua, ub = SoftUpdate(a, tau=0.05), ForeachSoftUpdate(b, tau=0.05)
    with torch.no_grad():
        for pa, pb in zip(a.parameters(), b.parameters()):
            noise = torch.randn_like(pa)
            pa.add_(noise), pb.add_(noise)
    for _ in range(3):
        ua.step(), ub.step()
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    # the actor's fixed bounds (buffers) are not "updated", as in torchrl
    assert len(ub._pairs()) == len(ua._sources.keys(True, True))


def test_adam_options_fused_on_cpu_params_only():
    p = torch.nn.Parameter(torch.zeros(3))
    assert adam_options([p]) == {"fused": True}
    assert adam_options([]) == {}
    assert adam_options([torch.zeros(3, dtype=torch.int64)]) == {}
    torch.optim.Adam([p], lr=1e-3, **adam_options([p])).step()  # accepted by torch


def test_buffer_batches_draw_what_buffer_sample_draws():
    data = _data(500)
    buffer = make_replay_buffer(data, batch_size=32)
    batches = BufferBatches(buffer)
    torch.manual_seed(5)
    expected = [buffer.sample().exclude("index") for _ in range(3)]
    torch.manual_seed(5)
    got = [batches.sample().clone() for _ in range(3)]
    for e, g in zip(expected, got):
        assert set(e.keys(True, True)) == set(g.keys(True, True))
        assert (e == g).all()


def test_buffer_batches_do_not_leak_entries_between_draws():
    batches = BufferBatches(make_replay_buffer(_data(100), batch_size=8))
    first = batches.sample()
    first.set("td_error", torch.zeros(8, 1))
    assert "td_error" not in batches.sample().keys()


def test_paired_sampler_draws_what_the_buffers_and_their_ensemble_draw():
    from torchrl.data import ReplayBufferEnsemble

    b, e = make_replay_buffer(_data(300)), make_replay_buffer(_data(120, seed=3).select("observation", "action"))
    sampler = PairedSampler(b, e, 16)
    keys = ("observation", "action")
    torch.manual_seed(2)
    by_buffer = TensorDict({"behaviour": b.sample(16).select(*keys), "expert": e.sample(16).select(*keys)}, [16])
    torch.manual_seed(2)
    pair = ReplayBufferEnsemble(b, e, sample_from_all=True, batch_size=32).sample()
    by_ensemble = TensorDict({"behaviour": pair[0].select(*keys), "expert": pair[1].select(*keys)}, [16])
    torch.manual_seed(2)
    got = sampler.sample()
    for expected in (by_buffer, by_ensemble):
        assert expected.batch_size == got.batch_size
        assert set(expected.keys(True, True)) == set(got.keys(True, True))
        assert (expected == got).all()


class _NoisyLinearPolicy(TensorDictModuleBase):
    """a = −Kx + 0.1·N(0, I) from torch's global generator (the rollouts must draw in the same order)."""

    def __init__(self, K):
        super().__init__()
        self.in_keys, self.out_keys = ["observation"], ["action"]
        self.K = K

    def forward(self, tensordict):
        x = tensordict.get("observation")
        return tensordict.set("action", -x @ self.K.T + 0.1 * torch.randn(x.shape[:-1] + (self.K.shape[0],)))


@pytest.mark.parametrize("batch, max_steps", [((), 20), ((1,), 5), ((7,), 20), ((3,), 50), ((2, 3), 20)])
def test_lqr_rollout_shortcut_equals_torchrl_rollout(batch, max_steps):
    from torchrl.envs import EnvBase

    from torchrl_wbrm.envs import LQREnv

    envs = [LQREnv("exp2", batch_size=batch, seed=3) for _ in range(2)]
    policy = _NoisyLinearPolicy(envs[0].riccati()[1].float())
    outs = []
    for env, rollout in zip(envs, (LQREnv.rollout, EnvBase.rollout)):
        torch.manual_seed(0)
        outs.append([rollout(env, max_steps, policy) for _ in range(2)])  # twice: the second starts from a reset
    for fast, slow in zip(*outs):
        assert type(fast) is type(slow)
        assert fast.batch_size == slow.batch_size and fast.names == slow.names and fast.device == slow.device
        assert set(fast.keys(True, True)) == set(slow.keys(True, True))
        assert all(torch.equal(fast.get(k), slow.get(k)) for k in slow.keys(True, True))
    assert torch.equal(envs[0]._step_count, envs[1]._step_count)
    assert torch.equal(envs[0].rng.get_state(), envs[1].rng.get_state())


class _ExtrasPolicy(_NoisyLinearPolicy):
    """Also writes a nested entry and replaces the ``"terminated"`` flag it is given by an equal new tensor."""

    def forward(self, tensordict):
        tensordict = super().forward(tensordict)
        tensordict.set(("policy", "scale"), tensordict.get("action").abs())
        return tensordict.set("terminated", tensordict.get("terminated").clone())


def test_lqr_rollout_shortcut_with_nested_and_replaced_entries_equals_torchrl_rollout():
    from torchrl.envs import EnvBase

    from torchrl_wbrm.envs import LQREnv

    envs = [LQREnv("exp1", batch_size=[5], seed=1) for _ in range(2)]
    policy = _ExtrasPolicy(envs[0].riccati()[1].float())
    outs = []
    for env, rollout in zip(envs, (LQREnv.rollout, EnvBase.rollout)):
        torch.manual_seed(0)
        outs.append(rollout(env, 20, policy))
    fast, slow = outs
    assert set(fast.keys(True, True)) == set(slow.keys(True, True)) and ("policy", "scale") in fast.keys(True, True)
    assert all(torch.equal(fast.get(k), slow.get(k)) for k in slow.keys(True, True))


def test_lqr_rollout_shortcut_checks_actions_and_refuses_flags_written_in_place():
    from torchrl_wbrm.envs import LQREnv

    class NaNFromThirdStep(TensorDictModuleBase):
        in_keys, out_keys = ["observation"], ["action"]

        def __init__(self):
            super().__init__()
            self.calls = 0

        def forward(self, tensordict):
            self.calls += 1
            a = torch.full(tensordict.batch_size + (2,), float("nan") if self.calls > 2 else 0.0)
            return tensordict.set("action", a)

    class WritesDone(TensorDictModuleBase):
        in_keys, out_keys = ["observation"], ["action"]

        def forward(self, tensordict):
            tensordict.get("done").fill_(True)
            return tensordict.set("action", torch.zeros(tensordict.batch_size + (2,)))

    env = LQREnv("exp1", batch_size=[4], seed=0)
    with pytest.raises(ValueError, match=r"'action' holds 144 non-finite value\(s\)"):
        env.rollout(20, NaNFromThirdStep())  # steps 3..20: 18 steps x 4 systems x 2 entries
    with pytest.raises(RuntimeError, match="wrote the done flags it was given in place"):
        env.rollout(20, WritesDone())


def test_lqr_rollout_other_arguments_take_torchrl_path():
    from torchrl_wbrm.envs import LQREnv

    env = LQREnv("exp1", batch_size=[2], seed=0)
    out = env.rollout(45, break_when_any_done=False)  # random actions, auto-reset after 20 steps
    assert out.shape == (2, 45)
    assert bool(out["next", "truncated"][:, 19].all()) and not bool(out["next", "truncated"][:, 20].any())


def test_trainer_divergence_check_on_cpu_is_first_non_finite(tmp_path):
    from tests.test_training import tiny_config
    from torchrl_wbrm.training import WBRMTrainer

    trainer = WBRMTrainer(tiny_config(), tmp_path / "run", progress=False)
    assert trainer.finite_watch({"loss": torch.tensor(1.0)}, read=False) is None
    name, value = trainer.finite_watch({"a": torch.tensor(1.0), "loss": torch.tensor(float("inf"))}, read=False)
    assert name == "loss" and value == float("inf")


def _sequential_pair():
    """A loss whose Q is a TensorDictSequential: NetworkCall makes the TensorDict call for it."""
    from tensordict.nn import TensorDictSequential

    torch.manual_seed(0)
    q = TensorDictSequential(make_q_network(3, 2, initial_bias=0.0, num_cells=(16, 16), activation="SiLU"))
    loss = WeightedBellmanLoss(q, actor_network=make_deterministic_actor(3, SPEC, num_cells=(16,)))
    loss.make_value_estimator(gamma=0.9)
    return loss


@pytest.mark.parametrize("path", ["tensor", "tensordict", "sequential"])
def test_priority_weight_and_input_checks_hold_on_every_network_call(path):
    from torchrl_wbrm.objectives import NonFiniteError

    if path == "sequential":
        loss = _sequential_pair()
        assert not loss._network_call("value_network").direct
    else:
        loss, slow = _pair()
        loss = loss if path == "tensor" else slow
        assert loss._network_call("value_network").direct == (path == "tensor")
    data = _data()
    p = torch.rand(64, generator=torch.Generator().manual_seed(2)) + 0.5
    q, y = loss.bellman_error(data)
    w = data["density_ratio"].squeeze(-1)
    with_p, figures = loss.value_loss(data.clone().set("priority_weight", p))
    torch.testing.assert_close(with_p, (w * p * (q - y).pow(2)).sum() / p.sum())  # TorchRL: Σ p l / Σ p
    torch.testing.assert_close(figures["weight_mean"], (w * p).mean())
    actor_loss = WeightedBellmanLoss.actor_loss  # the weighted actor loss reads the same product
    loss.weight_actor_loss = True
    weighted_actor, _ = actor_loss(loss, data.clone().set("priority_weight", p))
    loss.weight_actor_loss = False
    plain_actor, _ = actor_loss(loss, data.clone().set("priority_weight", p))
    assert not torch.equal(weighted_actor, plain_actor)
    bad = data.clone().set("priority_weight", -p)
    with pytest.raises(ValueError, match=r"Entry 'priority_weight' must be finite and non-negative"):
        loss.value_loss(bad)
    bad = data.clone()
    bad["observation"][0, 0] = float("nan")
    with pytest.raises(NonFiniteError, match=r"Entry 'observation' holds 1 non-finite"):
        loss.value_loss(bad)
    bad = data.clone()
    bad["density_ratio"][1] = -1.0
    with pytest.raises(ValueError, match=r"Entry 'density_ratio' must be finite and non-negative"):
        loss(bad)
    wide = data.clone()
    wide["observation"] = torch.randn(64, 4)
    wide["next", "observation"] = torch.randn(64, 4)
    with pytest.raises(ValueError, match=r"reads 5 input feature\(s\), but the batch gives 6"):
        loss.value_loss(wide)


def test_q_compile_is_not_a_setting():
    """The update has one eager path: ``q.compile`` is refused by the schema, from the command line and in Python."""
    from hydra.errors import ConfigCompositionException

    from references import compose_recipe
    from torchrl_wbrm.training.config import QConfig

    with pytest.raises(ConfigCompositionException, match=r"q\.compile"):
        compose_recipe("q.compile=true")
    with pytest.raises(TypeError, match=r"compile"):
        QConfig(compile=True)
