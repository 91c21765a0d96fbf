"""The action rescaling of TD3+BC, CQL and IQL (``torchrl_wbrm.modules.action_scaling``): the affine map between the
env's box and ``[−1, 1]ᵐ`` round-trips, the data enter the buffer in unit actions, the evaluated policy acts in the
box, and CQL's uniform actions (TorchRL's ``uniform_(−1, 1)``) cover the whole box once mapped back."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_wbrm.modules.action_scaling import ActionScaling
from torchrl_wbrm.training import WBRMTrainer

from tests.test_training import tiny_config


def test_rescaling_round_trips_and_maps_the_box_onto_the_unit_box():
    spec = Bounded(torch.tensor([-5.0, 0.0]), torch.tensor([5.0, 2.0]), shape=(2,))
    scaling = ActionScaling(spec)
    corners = torch.tensor([[-5.0, 0.0], [5.0, 2.0], [0.0, 1.0]])
    torch.testing.assert_close(scaling.to_unit(corners), torch.tensor([[-1.0, -1.0], [1.0, 1.0], [0.0, 0.0]]))
    a = torch.rand(1000, 2, generator=torch.Generator().manual_seed(0)) * torch.tensor([10.0, 2.0]) - torch.tensor([5.0, 0.0])
    torch.testing.assert_close(scaling.from_unit(scaling.to_unit(a)), a)
    u = 2 * torch.rand(1000, 2, generator=torch.Generator().manual_seed(1)) - 1
    torch.testing.assert_close(scaling.to_unit(scaling.from_unit(u)), u)
    assert scaling.unit_spec.is_in(u) and not scaling.unit_spec.is_in(torch.tensor([1.5, 0.0]))
    td = TensorDict({"action": a, "observation": torch.zeros(1000, 3)}, [1000])
    scaled = scaling.scale_data(td)
    torch.testing.assert_close(scaled["action"], scaling.to_unit(a))
    assert td["action"] is a  # the input is left as it was
    with pytest.raises(ValueError, match="finite box"):
        ActionScaling(Bounded(torch.tensor([0.0]), torch.tensor([0.0]), shape=(1,)))


@pytest.fixture(scope="module")
def trainers(tmp_path_factory):
    torch.set_num_threads(1)
    out = {}
    for algo in ("td3bc", "cql", "iql"):
        trainer = WBRMTrainer(tiny_config(algo=algo, baselines={"cql": {"num_random": 4}}),
                              tmp_path_factory.mktemp(algo), progress=False)
        trainer._build_q_buffer()
        out[algo] = trainer
    return out


@pytest.mark.parametrize("algo", ["td3bc", "cql", "iql"])
def test_data_enter_in_unit_actions_and_the_policy_acts_in_the_box(trainers, algo):
    trainer = trainers[algo]
    scaling = ActionScaling(trainer.action_spec)
    high = trainer.action_spec.space.high
    torch.testing.assert_close(trainer.q_buffer[:]["action"], scaling.to_unit(trainer.q_train_data["action"]))
    assert trainer.q_train_data["action"].abs().max() > 1.5  # LQR's box is [−5, 5]²: the rescaling is not a no-op
    obs = TensorDict({"observation": 3 * torch.randn(500, trainer.q_train_data["observation"].shape[-1])}, [500])
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        action = trainer.actor(obs.clone())["action"]
        unit = trainer.actor[0](obs.clone())["action"]  # the unit-action actor alone
    torch.testing.assert_close(action, scaling.from_unit(unit))
    assert bool((unit.abs() <= 1).all()) and bool((action.abs() <= high).all())
    # Q̂ is read at the box actions given (the rescaling is inside the reader)
    q, read_at = trainer.algo.q_value(trainer.q_train_data[:8])
    torch.testing.assert_close(read_at, trainer.q_train_data[:8]["action"])


def test_cql_random_actions_cover_the_env_box(trainers):
    trainer = trainers["cql"]
    loss, scaling = trainer.q_loss, ActionScaling(trainer.action_spec)
    seen = []
    vmapped = loss._vmap_qvalue_network00

    def record(td, params):
        seen.append(td["action"].detach().clone())
        return vmapped(td, params)

    torch.manual_seed(0)
    batch = trainer.q_buffer.sample(32)
    loss.q_loss(batch)  # writes the predictions cql_loss reads
    loss._vmap_qvalue_network00 = record
    try:
        loss.cql_loss(batch)
    finally:
        loss._vmap_qvalue_network00 = vmapped
    # Q sees the buffer's actions, which are the unit actions of the env's box (so [−1, 1] is the box) ...
    torch.testing.assert_close(trainer.q_buffer[:]["action"], scaling.to_unit(trainer.q_train_data["action"]))
    random_actions = seen[0][0]  # ... and the first block of the batched Q call: the uniform actions, first critic
    box = scaling.from_unit(random_actions)
    low, high = trainer.action_spec.space.low, trainer.action_spec.space.high
    assert bool(((box >= low) & (box <= high)).all())
    span = (box.max(0).values - box.min(0).values) / (high - low)
    assert bool((span > 0.9).all()), span  # 128 uniform draws per coordinate span > 90% of the box's width


def test_iql_policy_scale_is_state_independent(trainers):
    actor = trainers["iql"].q_loss.actor_network
    obs = TensorDict({"observation": torch.randn(64, trainers["iql"].q_train_data["observation"].shape[-1])}, [64])
    with torch.no_grad():
        dist = actor.get_dist(obs)
    scale = dist.base_dist.scale
    torch.testing.assert_close(scale, scale[:1].expand_as(scale))
    assert bool((dist.base_dist.loc.abs() <= 1).all())


def test_unit_q_network_reads_unit_actions_as_the_box_network_reads_box_actions():
    from torchrl_wbrm.modules import make_q_network

    spec = Bounded(-5.0, 5.0, (2,))
    scaling = ActionScaling(spec)
    q_box = make_q_network(3, 2, initial_bias=0.0, num_cells=(16,))
    q_unit = scaling.unit_q_network(q_box)
    g = torch.Generator().manual_seed(0)
    obs, a = torch.randn(64, 3, generator=g), 10 * torch.rand(64, 2, generator=g) - 5
    box = q_box(TensorDict({"observation": obs, "action": a}, [64]))["state_action_value"]
    unit = q_unit(TensorDict({"observation": obs, "action": scaling.to_unit(a)}, [64]))["state_action_value"]
    torch.testing.assert_close(unit, box)
    assert set(dict(q_unit.named_parameters())) == {f"module.net.{k}" for k, _ in q_box.module.named_parameters()}


def test_the_unit_action_maps_go_where_the_networks_are():
    """A Q network or an actor built on another device (``device=cuda``; here torch's ``meta`` device, which every
    machine has) gets the map's constants there too, so neither mixes devices in its forward pass."""
    from torchrl_wbrm.modules import make_deterministic_actor, make_q_network

    scaling = ActionScaling(Bounded(-2.0, 2.0, (2,)))
    q_unit = scaling.unit_q_network(make_q_network(3, 2, initial_bias=0.0, num_cells=(16,)).to("meta"))
    policy = scaling.policy(make_deterministic_actor(3, scaling.unit_spec, num_cells=(16,)).to("meta"))
    for module in (q_unit, policy):
        assert {t.device.type for t in (*module.parameters(), *module.buffers())} == {"meta"}
    td = TensorDict({"observation": torch.zeros(4, 3, device="meta"), "action": torch.zeros(4, 2, device="meta")}, [4])
    assert q_unit(td)["state_action_value"].shape == (4, 1)


@pytest.mark.parametrize("unit_input", [False, True])
def test_iql_q_reads_the_box_action_or_with_unit_action_input_the_unit_action(tmp_path, unit_input):
    trainer = WBRMTrainer(tiny_config(algo="iql", baselines={"iql": {"unit_action_input": unit_input}}), tmp_path,
                          progress=False)
    trainer._build_q_buffer()
    first = next(m for m in trainer.q_loss.qvalue_network.modules() if isinstance(m, torch.nn.Linear))
    seen = []
    hook = first.register_forward_pre_hook(lambda module, args: seen.append(args[0].detach().clone()))
    try:
        trainer.algo.q_value(trainer.q_train_data[:64])  # Q̂ at the data's box actions
    finally:
        hook.remove()
    m = trainer.action_spec.shape[-1]
    fed = seen[0][:, -m:]  # the first layer's input ends with the action (after the observation's fixed rescaling)
    box = trainer.q_train_data[:64]["action"]
    expected = ActionScaling(trainer.action_spec).to_unit(box) if unit_input else box
    torch.testing.assert_close(fed, expected)
    assert box.abs().max() > 1.5  # LQR's box is [−5, 5]²: the two inputs differ


def test_iql_critic_first_weights_the_actor_with_the_updated_value(tmp_path):
    trainer = WBRMTrainer(tiny_config(algo="iql", baselines={"iql": {"critic_first": True}}), tmp_path,
                          progress=False)
    trainer._build_q_buffer()
    loss = trainer.q_loss
    torch.manual_seed(0)
    batch = trainer.q_buffer.sample()
    actor0, target0 = loss.actor_network_params.data.clone(), loss.target_qvalue_network_params.data.clone()
    value0 = loss.value_network_params.data.clone()
    out = trainer.algo.step(batch.clone(), 0)
    with torch.no_grad():  # the actor loss it stepped: the actor and target Q before the step, V after it
        loss.actor_network_params.data.update_(actor0)
        loss.target_qvalue_network_params.data.update_(target0)
        with_new_value, _ = loss.actor_loss(batch.clone())
        loss.value_network_params.data.update_(value0)
        with_old_value, _ = loss.actor_loss(batch.clone())
    torch.testing.assert_close(out["loss_actor"], with_new_value)
    assert not torch.allclose(out["loss_actor"], with_old_value, rtol=1e-4, atol=0)
