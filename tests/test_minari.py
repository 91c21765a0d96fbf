"""env=minari: D, S^b and S^e from local Minari datasets, evaluation on the datasets' gymnasium env, clear errors.

The datasets are written here, on MountainCarContinuous-v0 (and Pendulum-v1 for the errors, CartPole-v1 with a
(2, 2) observation for a Discrete action and a multi-dimensional Box observation, a tiny uint8 (3, 4) "image" env),
with ``minari.create_dataset_from_buffers`` and ``EpisodeBuffer`` objects: that needs only ``minari[hdf5]``;
``minari.DataCollector`` would need jax. Nothing is downloaded.
"""
from __future__ import annotations


import gymnasium as gym
import numpy as np
import pytest
import torch

from minari_helpers import mountain_car_datasets
from torchrl_wbrm.tasks import EnvConfig, make_offline_datasets
from torchrl_wbrm.data.minari_data import (
    MinariDataConfig,
    make_minari_datasets,
    make_minari_eval_env,
    read_minari_transitions,
    resolve_minari_dataset,
    transitions_to_episodes,
    write_minari_dataset,
)
from torchrl_wbrm.data.minari_examples import PENDULUM, collect_gym_episodes, make_cartpole_datasets
from torchrl_wbrm.policies.gym_experts import cartpole_expert_action, pendulum_expert_action

#: the tiny uint8 "image" env's id (an observation of shape (3, 4), a Discrete(2) action)
IMAGE_ENV = "torchrl_wbrm_tests/TinyImage-v0"


class TinyImageEnv(gym.Env):
    """A uint8 ``(3, 4)`` observation (uniform pixels), ``Discrete(2)`` actions, 8 steps: reward 1 when the action
    says whether the mean pixel is above 127."""

    observation_space = gym.spaces.Box(0, 255, (3, 4), np.uint8)
    action_space = gym.spaces.Discrete(2)

    def _observe(self):
        self._obs = self.np_random.integers(0, 256, (3, 4), dtype=np.uint8)
        return self._obs

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._t = 0
        return self._observe(), {}

    def step(self, action):
        reward = float(int(action) == int(self._obs.mean() > 127))
        self._t += 1
        return self._observe(), reward, False, self._t >= 8, {}


@pytest.fixture(scope="session")
def cartpole_grid(tmp_path_factory) -> dict:
    """CartPole-v1 with its observation reshaped to (2, 2) (a Discrete(2) action): 10 expert episodes; a behaviour
    of 20 random and 20 epsilon-greedy (0.5) episodes. Written once per session."""
    root = tmp_path_factory.mktemp("minari_cartpole")
    return {"data_path": str(root), **make_cartpole_datasets(root, observation_shape=(2, 2), seed=0)}


def _cartpole_config(data: dict) -> MinariDataConfig:
    return MinariDataConfig(expert=data["expert"], behaviour=data["behaviour"], data_path=data["data_path"])


def _config(**kw) -> MinariDataConfig:
    data = mountain_car_datasets()
    base = dict(expert=data["expert"], behaviour=data["behaviour"], data_path=data["data_path"])
    return MinariDataConfig(**{**base, **kw})


def test_split_by_episode_and_spaces():
    datasets = make_minari_datasets(_config(), seed=0)
    d, sb, se = (getattr(datasets, n)[:] for n in ("transitions", "behaviour_samples", "expert_samples"))
    assert set(d["episode"].tolist()).isdisjoint(sb["episode"].tolist())
    meta = datasets.metadata
    assert meta["eval_env"] == "MountainCarContinuous-v0" and meta["max_episode_steps"] == 999
    assert meta["action_low"] == [-1.0] and meta["action_high"] == [1.0]
    assert d["observation"].dtype == torch.float32 and d["action"].shape[-1] == 1
    from minari.dataset.minari_dataset import MinariDataset

    assert se.shape[0] == MinariDataset(meta["expert_path"]).total_steps  # every expert step is in S^e
    assert d.shape[0] + sb.shape[0] == MinariDataset(meta["behaviour_path"]).total_steps
    # the same through the env factory (env.kind="minari"), and the data cache does not copy local datasets
    again = make_offline_datasets(EnvConfig(name="minari", kind="minari", minari=_config()), seed=0)
    assert torch.equal(again.transitions[:]["observation"], d["observation"])


def test_round_trip_of_episodes(tmp_path, monkeypatch):
    episodes = collect_gym_episodes(PENDULUM, lambda obs, rng: pendulum_expert_action(obs), 2, seed=3)
    monkeypatch.chdir(tmp_path)  # a relative data path (Minari's writer needs it made absolute)
    ds = write_minari_dataset("rt/pendulum-v0", episodes, data_path=".", env=PENDULUM, eval_env=PENDULUM)
    td = read_minari_transitions(ds)
    assert td.shape[0] == sum(len(e["rewards"]) for e in episodes) == 400
    np.testing.assert_allclose(td["observation"][:200].numpy(), episodes[0]["observations"][:-1], rtol=1e-6)
    np.testing.assert_allclose(td["next", "reward"][200:, 0].numpy(), episodes[1]["rewards"], rtol=1e-6)
    assert bool(td["next", "truncated"][199]) and not bool(td["next", "terminated"].any())
    back = transitions_to_episodes(td)
    assert len(back) == 2 and back[1]["observations"].shape == (201, 3)
    # a local path works as well as an id under the data path
    assert resolve_minari_dataset(str(tmp_path / "rt" / "pendulum-v0")) == tmp_path / "rt" / "pendulum-v0" / "data"


def test_missing_dataset_names_id_and_data_path(tmp_path):
    with pytest.raises(FileNotFoundError) as err:
        make_minari_datasets(MinariDataConfig(expert="nowhere/expert-v0", behaviour="nowhere/behaviour-v0",
                                              data_path=str(tmp_path)))
    message = str(err.value)
    assert "'nowhere/expert-v0'" in message and f"Minari data path {tmp_path}" in message
    assert "minari download" in message  # how to fetch it; nothing is downloaded at run time


def test_mismatched_spaces_name_both(tmp_path):
    episodes = collect_gym_episodes(PENDULUM, lambda obs, rng: pendulum_expert_action(obs), 1, seed=0)
    write_minari_dataset("other/pendulum-v0", episodes, data_path=tmp_path, env=PENDULUM, eval_env=PENDULUM)
    data = mountain_car_datasets()
    with pytest.raises(ValueError) as err:
        make_minari_datasets(MinariDataConfig(expert=str(tmp_path / "other" / "pendulum-v0"),
                                              behaviour=data["behaviour_path"]))
    message = str(err.value)
    assert "observation spaces" in message
    assert "Box([-1. -1. -8.], [1. 1. 8.], (3,), float32)" in message  # Pendulum's
    assert "Box([-1.2  -0.07], [0.6  0.07], (2,), float32)" in message  # MountainCar's


def test_eval_env_recorded_or_given(tmp_path):
    from gymnasium import spaces

    episodes = collect_gym_episodes(PENDULUM, lambda obs, rng: pendulum_expert_action(obs), 4, seed=0)  # min_behaviour_episodes
    write_minari_dataset("anon/expert-v0", episodes, data_path=tmp_path,
                         observation_space=spaces.Box(np.array([-1, -1, -8], np.float32),
                                                      np.array([1, 1, 8], np.float32)),
                         action_space=spaces.Box(-2.0, 2.0, (1,), np.float32))
    cfg = MinariDataConfig(expert="anon/expert-v0", behaviour="anon/expert-v0", data_path=str(tmp_path))
    meta = make_minari_datasets(cfg).metadata
    assert meta["eval_env"] is None
    with pytest.raises(ValueError, match="env.minari.eval_env"):
        make_minari_eval_env(meta)
    cfg.eval_env = PENDULUM
    env = make_minari_eval_env(make_minari_datasets(cfg).metadata)
    assert env.action_spec.shape[-1] == 1


def test_multidimensional_observation_read_flat_and_evaluated_alike(cartpole_grid):
    """A (2, 2) Box observation: read flattened row-major; the evaluation env, recovered from the dataset's recorded
    spec even where the env id is not registered, flattens its observation the same way."""
    from minari.dataset.minari_dataset import MinariDataset

    datasets = make_minari_datasets(_cartpole_config(cartpole_grid))
    meta = datasets.metadata
    assert meta["observation_shape"] == [2, 2] and meta["discrete_actions"] == 2
    episode = next(MinariDataset(meta["behaviour_path"]).iterate_episodes())
    read = read_minari_transitions(MinariDataset(meta["behaviour_path"]))
    assert read["observation"].shape[-1] == 4 and read["observation"].dtype == torch.float32
    np.testing.assert_array_equal(read["observation"][: len(episode.rewards)].numpy(),
                                  episode.observations[:-1].reshape(-1, 4))
    spec = gym.registry.pop(cartpole_grid["env"])  # as in a fresh process: only the recorded spec knows the env
    try:
        env = make_minari_eval_env(meta, seed=0)
    finally:
        gym.registry[cartpole_grid["env"]] = spec
    assert env.observation_spec["observation"].shape == (4,)
    td = env.reset()
    state = env.base_env._env.unwrapped.state  # CartPole's (x, ẋ, θ, θ̇)
    np.testing.assert_allclose(td["observation"].numpy(), np.asarray(state, dtype=np.float32), rtol=1e-6)
    # the expert heuristic, reading the flat vector, keeps the pole up in the evaluation env
    from tensordict.nn import TensorDictModule

    from torchrl_wbrm.evaluation import evaluate_returns

    def scores(obs):
        return torch.nn.functional.one_hot(torch.tensor(cartpole_expert_action(obs.numpy())), 2).float()

    assert evaluate_returns(env, TensorDictModule(scores, ["observation"], ["action"]), episodes=1, seed=0).mean == 500
    # an evaluation env whose observation is not the datasets' shape is refused, naming both
    with pytest.raises(ValueError, match=r"'CartPole-v1' has observations of shape \(4,\), the Minari datasets' of shape \(2, 2\)"):
        make_minari_eval_env({**meta, "eval_env": "CartPole-v1", "eval_env_spec": None})


def test_multidimensional_box_action_read_flat_and_reshaped_for_the_env(tmp_path):
    """Pendulum-v1 with its Box action reshaped to (1, 1): the data's actions are read flat, (N, 1); the evaluation
    env takes the policy's flat action and steps gym with it reshaped back, so the swing-up heuristic scores there
    what it scored in the data; an env whose action space is not the datasets' is refused, naming both."""
    from torchrl_wbrm.data.minari_examples import register_reshaped_env

    env_id = register_reshaped_env("Pendulum-v1", action_shape=(1, 1))
    assert gym.make(env_id).action_space.shape == (1, 1)
    episodes = collect_gym_episodes(env_id, lambda obs, rng: pendulum_expert_action(obs).reshape(1, 1), 6, seed=0)
    for name in ("expert", "behaviour"):
        write_minari_dataset(f"pendulum_a1x1/{name}-v0", episodes, data_path=tmp_path, env=env_id)
    data = make_minari_datasets(MinariDataConfig(expert="pendulum_a1x1/expert-v0", behaviour="pendulum_a1x1/behaviour-v0",
                                                 data_path=str(tmp_path)))
    meta = data.metadata
    assert meta["action_shape"] == [1, 1] and meta["action_low"] == [-2.0] and meta["action_high"] == [2.0]
    expert = data.expert_samples[:]
    assert expert["action"].shape == (expert.shape[0], 1)
    np.testing.assert_allclose(expert["action"][:3, 0].numpy(),
                               np.asarray(episodes[0]["actions"], np.float32)[:3].reshape(-1), rtol=1e-6)
    env = make_minari_eval_env(meta)
    assert tuple(env.action_spec.shape) == (1,)
    from tensordict.nn import TensorDictModule

    from torchrl_wbrm.evaluation import evaluate_returns

    # one step with a flat action reaches gym reshaped and unchanged: the same state stepped in plain Pendulum-v1
    td = env.reset()
    raw = gym.make("Pendulum-v1")
    raw.reset(seed=0)
    from torchrl.envs import TransformedEnv

    gym_env = (env.base_env if isinstance(env, TransformedEnv) else env)._env
    raw.unwrapped.state = np.array(gym_env.unwrapped.state)
    td["action"] = torch.tensor([1.5])
    out = env.step(td)["next"]
    obs, reward, *_ = raw.step(np.array([1.5], np.float32))
    np.testing.assert_allclose(out["observation"].numpy(), obs, rtol=1e-6)
    assert out["reward"].item() == pytest.approx(float(reward), rel=1e-6)

    def act(obs):
        return torch.as_tensor(pendulum_expert_action(obs.numpy()))

    def zero(obs):
        return torch.zeros(1)

    swing_up = evaluate_returns(env, TensorDictModule(act, ["observation"], ["action"]), episodes=4, seed=0).mean
    idle = evaluate_returns(env, TensorDictModule(zero, ["observation"], ["action"]), episodes=4, seed=0).mean
    assert swing_up > idle + 300  # the policy's actions drive the env (same start states)
    with pytest.raises(ValueError, match=r"'Pendulum-v1' has the action space Box\(-2.0, 2.0, \(1,\), float32\), the Minari datasets' is Box"):
        make_minari_eval_env({**meta, "eval_env": "Pendulum-v1", "eval_env_spec": None})
    # the recipe's trainer runs on them and evaluates through that env (its actor acts in the flat box)
    from torchrl_wbrm.training import WBRMTrainer

    minari = MinariDataConfig(expert="pendulum_a1x1/expert-v0", behaviour="pendulum_a1x1/behaviour-v0",
                              data_path=str(tmp_path))
    results = WBRMTrainer(_tiny_trainer_config(minari), tmp_path / "run", progress=False).run()
    assert results["status"] == "finished" and np.isfinite(results["final"]["return"])


def _tiny_trainer_config(minari: MinariDataConfig) -> dict:
    return {"env": {"name": "tiny", "kind": "minari", "minari": vars(minari)}, "ratio": {"steps": 4, "eval_every": 2,
            "batch_size": 32, "num_cells": [8]}, "q": {"steps": 4, "eval_every": 4, "batch_size": 32,
            "num_cells": [8], "actor_num_cells": [8], "gamma": 0.99}, "eval": {"episodes": 2, "train_episodes": 1},
            "plots": False, "checkpoint_every": 0, "threads": 1}


def test_image_like_observation_and_discrete_action_run(tmp_path, single_thread):
    """A uint8 (3, 4) observation and a Discrete(2) action: read as 12 float32 numbers and one-hot actions; the
    recipe's trainer runs on them (wbrm: a Q head over the two actions, no actor; dqn: the two actions as its grid)
    and evaluates on the env, which casts and flattens its observation alike."""
    from torchrl_wbrm.training import WBRMTrainer

    gym.register(IMAGE_ENV, entry_point=f"{__name__}:TinyImageEnv")
    try:
        episodes = collect_gym_episodes(IMAGE_ENV, lambda obs, rng: int(rng.integers(0, 2)), 6, seed=0)
        write_minari_dataset("tiny/random-v0", episodes, data_path=tmp_path, env=IMAGE_ENV, eval_env=IMAGE_ENV)
        minari = MinariDataConfig(expert="tiny/random-v0", behaviour="tiny/random-v0", data_path=str(tmp_path))
        datasets = make_minari_datasets(minari)
        d = datasets.transitions[:]
        assert d["observation"].shape[-1] == 12 and d["observation"].dtype == torch.float32
        assert d["observation"].max() > 1.0  # pixel values, not rescaled
        assert torch.equal(d["action"].sum(-1), torch.ones(d.shape[0]))  # one-hot
        env = make_minari_eval_env(datasets.metadata)
        assert env.observation_spec["observation"].shape == (12,)
        assert env.observation_spec["observation"].dtype == torch.float32
        trainer = WBRMTrainer(_tiny_trainer_config(minari), tmp_path / "run", progress=False)
        results = trainer.run()
        # the actor's settings are refused: a Discrete action has no actor
        cloning = _tiny_trainer_config(minari)
        cloning["q"] = {**cloning["q"], "bc_alpha": 2.5}
        with pytest.raises(ValueError, match=r"q.bc_alpha=2.5 configures the actor, but a Discrete\(2\) action"):
            WBRMTrainer(cloning, tmp_path / "cloning", progress=False).run()
        # algo=dqn: its "grid" is the two actions themselves
        dqn = WBRMTrainer({**_tiny_trainer_config(minari), "algo": "dqn"}, tmp_path / "dqn", progress=False).run()
    finally:
        gym.registry.pop(IMAGE_ENV, None)
    assert not trainer.algo.loss.has_actor  # greedy in Q over the two actions
    for res in (results, dqn):
        assert res["status"] == "finished" and 0.0 <= res["final"]["return"] <= 8.0


@pytest.mark.parametrize("algo", ["wbrm", "brm", "iql", "bc", "ddpg"])
def test_minari_defaults_follow_the_action_space_and_the_algo(cartpole_grid, algo):
    """A continuous action gets the Minari defaults (LayerNorm, 9,000 steps, the held-out weighted residual's pick)
    for an algo that fits a Bellman residual, the LayerNorm and the shared selection for DDPG, and the shared
    LayerNorm and selection for the others; a Discrete action keeps the shared defaults. The command line wins over
    either."""
    from torchrl_wbrm.tasks import MinariTask, Task
    from torchrl_wbrm.training import WBRMConfig
    from torchrl_wbrm.training.config import to_config

    def resolved(data: MinariDataConfig, **q):
        cfg = WBRMConfig(env="minari", algo=algo)
        cfg.env.minari.expert, cfg.env.minari.behaviour = data.expert, data.behaviour
        cfg.env.minari.data_path = data.data_path
        for key, value in q.items():
            setattr(cfg.q, key, value)
        out = to_config(cfg).q
        return out.layer_norm, out.steps, out.eval_every, out.select

    residual = algo in ("wbrm", "brm")
    shared = Task.TRAINING_DEFAULTS.q
    continuous = MinariTask.TRAINING_DEFAULTS.q
    assert continuous.steps == 9000 and continuous.select == "held_out_weighted_residual"
    pick = (continuous if residual else shared)
    layer_norm = (continuous if residual or algo == "ddpg" else shared).layer_norm
    assert layer_norm is (residual or algo == "ddpg")
    assert resolved(_config()) == (layer_norm, 9000, 1500, pick.select)
    assert resolved(_cartpole_config(cartpole_grid)) == (False, 3000, 500, "last")
    assert resolved(_config(), layer_norm=False, steps=7, select="last") == (False, 7, 1500, "last")


@pytest.mark.slow
def test_discrete_action_learning(tmp_path, cartpole_grid, single_thread):
    """WBRM on the CartPole (2, 2)-observation datasets closes at least half the gap from the behaviour data's mean
    return to the expert data's (lower 95% bound; measured seed 0: 500 ± 0 against 93.7 and 482.3)."""
    from torchrl_wbrm.training import WBRMTrainer

    cfg = {"env": {"name": "cartpole", "kind": "minari", "minari": vars(_cartpole_config(cartpole_grid))},
           "ratio": {"steps": 100, "eval_every": 50, "batch_size": 256, "num_cells": [64, 64]},
           "q": {"steps": 1000, "eval_every": 1000, "num_cells": [64, 64], "gamma": 0.99,
                 "normalise_observations": True},  # configs/env/minari.yaml's
           "eval": {"episodes": 5, "train_episodes": 3}, "plots": False, "checkpoint_every": 0, "threads": 1}
    results = WBRMTrainer(cfg, tmp_path / "run", progress=False).run()
    final, data = results["final"], results["data"]
    behaviour, expert = data["behaviour_mean_return"], data["expert_mean_return"]
    assert results["status"] == "finished" and behaviour < expert
    assert final["return"] - final["return_ci"] > behaviour + 0.5 * (expert - behaviour), (final, data)


def test_console_verbose_switch(caplog):
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

    from torchrl_wbrm.training.logging import configure_console

    def storage_lines() -> int:
        caplog.clear()
        TensorDictReplayBuffer(storage=LazyTensorStorage(4)).extend(TensorDict({"x": torch.zeros(4)}, [4]))
        return sum("Initialized LazyTensorStorage" in r.getMessage() for r in caplog.records)

    try:
        configure_console(False)
        assert storage_lines() == 0
        configure_console(True)
        assert storage_lines() == 1
    finally:
        configure_console(False)


@pytest.mark.parametrize("env_name", ["lqr_exp1", "mountain_car"])
def test_make_dataset_writes_minari(tmp_path, env_name):
    """recipes/make_dataset.py format=minari: the project's own collections as Minari datasets, read back whole."""
    from omegaconf import OmegaConf

    from torchrl_wbrm import cli as recipe
    from torchrl_wbrm.training.config import MakeDatasetConfig

    sizes = {"lqr_exp1": {"env.kind": "lqr", "env.lqr_data.behaviour_episodes": 20, "env.lqr_data.expert_episodes": 10,
                          "env.lqr_data.parallel_envs": 10},
             "mountain_car": {"env.kind": "mountain_car", "env.mountain_car_data.expert_transitions": 400,
                              "env.mountain_car_data.behaviour_transitions": 1200}}[env_name]
    cfg = OmegaConf.merge(OmegaConf.structured(MakeDatasetConfig),
                          OmegaConf.from_dotlist([f"env.name={env_name}", "format=minari",
                                                  *(f"{k}={v}" for k, v in sizes.items())]))
    recipe._write_minari(cfg, tmp_path)
    own = make_offline_datasets(cfg.env, seed=0)
    minari = MinariDataConfig(expert=f"make_dataset/{env_name}_seed0/expert-v0",
                              behaviour=f"make_dataset/{env_name}_seed0/behaviour-v0", data_path=str(tmp_path))
    back = make_minari_datasets(minari, seed=0)
    own_sizes, back_sizes = own.sizes(), back.sizes()
    assert back_sizes["expert_samples"] == own_sizes["expert_samples"]
    assert (back_sizes["transitions"] + back_sizes["behaviour_samples"]
            == own_sizes["transitions"] + own_sizes["behaviour_samples"])
    if env_name == "mountain_car":  # both undiscounted (LQR's own metadata hold discounted returns)
        for key in ("behaviour_mean_return", "expert_mean_return"):
            assert back.metadata[key] == pytest.approx(own.metadata[key], rel=1e-5), key
    else:
        assert 150 < back.metadata["behaviour_mean_return"] < back.metadata["expert_mean_return"] < 200
    torch.testing.assert_close(back.expert_samples[:]["observation"].sort(0).values,
                               own.expert_samples[:]["observation"].sort(0).values)
    assert back.metadata["eval_env"] == ("MountainCarContinuous-v0" if env_name == "mountain_car" else None)


@pytest.mark.parametrize("env_id,action_shape", [("Pendulum-v1", (1, 1)), ("InvertedPendulum-v5", None)])
def test_the_vector_env_gives_the_one_by_one_figures(tmp_path, env_id, action_shape):
    """Evaluation runs every episode at once in a vector env (the policy acts on the batch): each episode's return
    equals the one of the single env seeded ``seed + i``, to the last bit, whatever the episodes' lengths; an
    InvertedPendulum policy whose episodes end at different steps checks the end of each episode."""
    import importlib.util

    from tensordict.nn import TensorDictModule

    from torchrl_wbrm.data.minari_examples import register_reshaped_env
    from torchrl_wbrm.tasks import MinariEvaluator
    from torchrl_wbrm.evaluation import evaluate_returns
    from torchrl_wbrm.evaluation.metrics import discounted_returns

    if env_id.startswith("Inverted") and importlib.util.find_spec("mujoco") is None:
        pytest.skip("needs mujoco")
    if action_shape is not None:
        env_id = register_reshaped_env(env_id, action_shape=action_shape)
        act = np.zeros(action_shape, np.float32)
    else:
        act = np.zeros(gym.make(env_id).action_space.shape, np.float32)
    episodes = collect_gym_episodes(env_id, lambda obs, rng: act + rng.uniform(-1, 1, act.shape).astype(np.float32),
                                    4, seed=0)
    write_minari_dataset("vec/expert-v0", episodes, data_path=tmp_path, env=env_id)
    meta = make_minari_datasets(MinariDataConfig(expert="vec/expert-v0", behaviour="vec/expert-v0",
                                                 data_path=str(tmp_path))).metadata
    def act_batch(observation):  # a plain function of the observation, for one or a batch
        return 0.5 * torch.tanh(3 * observation[..., :1])

    policy = TensorDictModule(act_batch, in_keys=["observation"], out_keys=["action"])
    single = make_minari_eval_env(meta)
    one_by_one = []
    for i in range(5):
        single.set_seed(11 + i)
        one_by_one.append(float(discounted_returns(single.rollout(1000, policy), 1.0)))
    vector = make_minari_eval_env(meta, num_envs=5)
    assert tuple(vector.batch_size) == (5,)
    at_once = evaluate_returns(vector, policy, episodes=5, seed=11)
    assert at_once.mean == pytest.approx(np.mean(one_by_one), abs=1e-9)
    evaluator = MinariEvaluator(meta)
    assert evaluator.evaluate(policy, episodes=5, seed=11)["return"] == pytest.approx(np.mean(one_by_one), abs=1e-9)
    if env_id.startswith("Inverted"):
        assert len({round(r) for r in one_by_one}) > 1, one_by_one  # episodes of different lengths
    with pytest.raises(ValueError, match="num_envs must be a positive integer"):
        make_minari_eval_env(meta, num_envs=0)
