"""Offline datasets: collection, the D / S^b / S^e split, paired sampling, save/load and its errors."""
from __future__ import annotations

import json
import shutil

import pytest
import torch
from tensordict import TensorDict

from torchrl_wbrm.data import (
    LQRDataConfig,
    MountainCarDataConfig,
    OfflineDatasets,
    collect_transitions,
    episode_returns,
    make_lqr_datasets,
    make_mountain_car_datasets,
    split_by_episode,
)
from torchrl_wbrm.envs import make_lqr_env
from torchrl_wbrm.policies import make_lqr_behaviour

SMALL = LQRDataConfig(behaviour_episodes=60, expert_episodes=30, parallel_envs=30)


@pytest.fixture(scope="module")
def lqr_data():
    return make_lqr_datasets("exp1", SMALL, seed=0)


def test_sizes_and_split_are_disjoint_by_episode(lqr_data):
    sizes = lqr_data.sizes()
    assert sizes["transitions"] + sizes["behaviour_samples"] == 60 * 20
    assert sizes["expert_samples"] == 30 * 20
    d_eps = set(lqr_data.transitions[:]["episode"].tolist())
    s_eps = set(lqr_data.behaviour_samples[:]["episode"].tolist())
    assert d_eps.isdisjoint(s_eps) and len(d_eps) == len(s_eps) == 30


def test_collected_episodes_are_whole_and_in_order():
    env = make_lqr_env("exp1", batch_size=[7], seed=0)
    data = collect_transitions(env, make_lqr_behaviour(env), 7 * 20 * 3, seed=1)
    assert data.shape == (7 * 20 * 3,)
    for ep in torch.unique(data["episode"])[:5]:
        steps = data[data["episode"] == ep]["step_count"].squeeze(-1)
        assert steps.tolist() == list(range(20))
        tr = data[data["episode"] == ep]
        assert (tr["observation"][1:] == tr["next", "observation"][:-1]).all()
        assert tr["next", "truncated"][-1].item() and not tr["next", "done"][:-1].any()


def test_policy_noise_is_independent_of_env_noise():
    """Regression: seeding the env and torch's generator alike made action noise equal the initial-state draw."""
    env = make_lqr_env("exp1", batch_size=[5000], seed=4)
    policy = make_lqr_behaviour(env)
    data = collect_transitions(env, policy, 5000 * 20, seed=4)
    first = data[data["step_count"].squeeze(-1) == 0]
    noise = first["action"] + first["observation"] @ policy.module.gain.T
    corr = torch.corrcoef(torch.stack([noise[:, 0], first["observation"][:, 0]]))[0, 1]
    assert abs(corr.item()) < 0.05


def test_same_seed_same_data_and_different_seed_differs():
    a = make_lqr_datasets("exp2", SMALL, seed=3)
    b = make_lqr_datasets("exp2", SMALL, seed=3)
    c = make_lqr_datasets("exp2", SMALL, seed=4)
    for part in ("transitions", "behaviour_samples", "expert_samples"):
        assert (getattr(a, part)[:]["action"] == getattr(b, part)[:]["action"]).all()
    assert not torch.equal(a.expert_samples[:]["action"], c.expert_samples[:]["action"])


def test_expert_samples_follow_the_expert(lqr_data):
    env = make_lqr_env("exp1")
    _, K = env.base_env.riccati()
    e = lqr_data.expert_samples[:]
    residual = e["action"] + e["observation"] @ (0.95 * K).float().T
    assert abs(residual.std().item() - 0.05) < 0.01
    assert lqr_data.metadata["expert_mean_return"] > lqr_data.metadata["behaviour_mean_return"]


def test_paired_sampler(lqr_data):
    sampler = lqr_data.paired_sampler(16)
    torch.manual_seed(0)
    batch = sampler.sample().clone()  # the next draw overwrites the sampler's batch
    assert batch.batch_size == (16,)
    assert set(batch.keys()) == {"behaviour", "expert"}
    assert batch["behaviour", "observation"].shape == (16, 2) and batch["expert", "action"].shape == (16, 2)
    expert_actions = lqr_data.expert_samples[:]["action"]
    # every expert row of the batch is a row of S^e
    assert all((expert_actions == row).all(-1).any() for row in batch["expert", "action"])
    torch.manual_seed(0)
    again = sampler.sample()
    assert (again["behaviour", "action"] == batch["behaviour", "action"]).all()


def test_save_load_round_trip(tmp_path, lqr_data):
    lqr_data.save(tmp_path / "ds")
    loaded = OfflineDatasets.load(tmp_path / "ds")
    assert loaded.sizes() == lqr_data.sizes()
    for part in ("transitions", "behaviour_samples", "expert_samples"):
        assert (getattr(loaded, part)[:] == getattr(lqr_data, part)[:]).all()
    assert loaded.metadata["seed"] == 0 and loaded.metadata["env"] == "lqr"
    memmapped = OfflineDatasets.load(tmp_path / "ds", storage="memmap", scratch_dir=tmp_path / "scratch")
    assert (memmapped.transitions[:]["observation"] == lqr_data.transitions[:]["observation"]).all()


def test_load_errors(tmp_path, lqr_data):
    with pytest.raises(FileNotFoundError, match=r"No dataset directory at .*nowhere"):
        OfflineDatasets.load(tmp_path / "nowhere")
    root = lqr_data.save(tmp_path / "ds")
    meta = root / "metadata.json"
    original = meta.read_text()
    meta.write_text("{not json")
    with pytest.raises(ValueError, match="Corrupt dataset.*metadata.json"):
        OfflineDatasets.load(root)
    meta.write_text(json.dumps({**json.loads(original), "format_version": 99}))
    with pytest.raises(ValueError, match="format_version 99"):
        OfflineDatasets.load(root)
    meta.write_text(json.dumps({**json.loads(original), "sizes": {"transitions": 3}}))
    with pytest.raises(ValueError, match="'transitions' holds"):
        OfflineDatasets.load(root)
    meta.write_text(original)
    shutil.rmtree(root / "expert_samples")
    with pytest.raises(FileNotFoundError, match=r"ds.* is missing its 'expert_samples' part"):
        OfflineDatasets.load(root)
    meta.unlink()
    with pytest.raises(FileNotFoundError, match=r"ds.*no metadata\.json"):
        OfflineDatasets.load(root)


def test_incompatible_and_empty_sets(lqr_data):
    d, b, e = (getattr(lqr_data, p)[:] for p in ("transitions", "behaviour_samples", "expert_samples"))
    wrong = TensorDict(observation=e["observation"], action=torch.zeros(e.shape[0], 3), batch_size=e.shape)
    with pytest.raises(ValueError, match="Incompatible datasets: the expert_samples"):
        OfflineDatasets.from_tensordicts(d, b, wrong)
    with pytest.raises(ValueError, match="expert_samples set is empty"):
        OfflineDatasets.from_tensordicts(d, b, e[:0])
    with pytest.raises(KeyError, match=r"transitions set lacks the keys .*next.*reward"):
        OfflineDatasets.from_tensordicts(d.exclude(("next", "reward")), b, e)
    with pytest.raises(KeyError, match=r"expert_samples set lacks the keys \W*action"):
        OfflineDatasets.from_tensordicts(d, b, e.exclude("action"))


def test_split_by_episode_errors():
    td = TensorDict(episode=torch.zeros(4, dtype=torch.int64), batch_size=[4])
    with pytest.raises(ValueError, match="at least 2 episodes"):
        split_by_episode(td, 0.5)
    with pytest.raises(ValueError, match="fraction"):
        split_by_episode(td, 1.0)
    with pytest.raises(KeyError, match="needs an 'episode' entry"):
        split_by_episode(TensorDict(batch_size=[4]), 0.5)


def test_episode_returns_known_answer():
    td = TensorDict(
        {
            "episode": torch.tensor([0, 0, 0, 1, 1, 2]),
            ("next", "reward"): torch.tensor([[1.0], [2.0], [4.0], [3.0], [5.0], [7.0]]),
            ("next", "done"): torch.tensor([[False], [False], [True], [False], [True], [False]]),
        },
        batch_size=[6],
    )
    torch.testing.assert_close(episode_returns(td, gamma=0.5), torch.tensor([1 + 1 + 1.0, 3 + 2.5], dtype=torch.float64))
    torch.testing.assert_close(episode_returns(td), torch.tensor([7.0, 8.0], dtype=torch.float64))  # episode 2 is partial


def test_mountain_car_dataset_shape():
    ds = make_mountain_car_datasets(
        MountainCarDataConfig(expert_transitions=600, behaviour_transitions=2400, random_fraction=0.5, ratio_fraction=0.3),
        seed=0,
    )
    sizes = ds.sizes()
    assert sizes["expert_samples"] == 600
    assert sizes["transitions"] + sizes["behaviour_samples"] == 2400
    d = ds.transitions[:]
    assert d["observation"].shape[-1] == 2 and d["action"].shape[-1] == 1
    assert ds.metadata["expert_mean_return"] > 80
    assert "behaviour_mean_return" in ds.metadata


def test_mountain_car_dataset_on_parallel_cars():
    ds = make_mountain_car_datasets(
        MountainCarDataConfig(expert_transitions=4000, behaviour_transitions=8000, ratio_fraction=0.3, parallel_envs=4),
        seed=1,
    )
    assert ds.metadata["data_config"]["parallel_envs"] == 4
    assert ds.sizes()["expert_samples"] == 4000
    assert ds.sizes()["transitions"] + ds.sizes()["behaviour_samples"] == 8000
    d, b = ds.transitions[:], ds.behaviour_samples[:]
    assert not set(d["episode"].tolist()) & set(b["episode"].tolist())
    # every episode id is one car's run: within an id, transitions chain in time and only the last may be done
    order = torch.argsort(d["episode"], stable=True)
    d = d[order]
    same = d["episode"][1:] == d["episode"][:-1]
    assert (d["next", "observation"][:-1][same] == d["observation"][1:][same]).all()
    assert not d["next", "done"][:-1].squeeze(-1)[same].any()
    # random episodes (truncated at 999 steps, about -33) and expert ones (about 93) are both in the behaviour data
    returns = episode_returns(d)
    assert (returns < 0).any() and (returns > 90).any()
    assert 90 < ds.metadata["expert_mean_return"] < 96


def test_mountain_car_parallel_envs_must_be_positive():
    with pytest.raises(ValueError, match="parallel_envs must be a positive integer"):
        make_mountain_car_datasets(MountainCarDataConfig(parallel_envs=0))


def test_cached_datasets_are_reused_and_keyed_by_config(tmp_path):
    from torchrl_wbrm.tasks import EnvConfig, cached_offline_datasets

    env = EnvConfig(lqr_data=SMALL)
    a = cached_offline_datasets(env, seed=0, cache_dir=tmp_path)
    b = cached_offline_datasets(env, seed=0, cache_dir=tmp_path)
    assert (a.transitions[:]["action"] == b.transitions[:]["action"]).all()
    assert len(list(tmp_path.iterdir())) == 1
    cached_offline_datasets(env, seed=1, cache_dir=tmp_path)
    other = EnvConfig(lqr_data=LQRDataConfig(behaviour_episodes=40, expert_episodes=30, parallel_envs=30))
    cached_offline_datasets(other, seed=0, cache_dir=tmp_path)
    assert len([p for p in tmp_path.iterdir() if not p.name.startswith(".")]) == 3


def test_a_shifted_behaviour_start_moves_the_behaviour_data_only():
    """``behaviour_initial_std``: the behaviour episodes start from N(0, s² I), the expert's (and the metadata's
    optimum, the evaluation's start law) keep the system's; the evaluator's behaviour samples follow the shift; a
    value that is not a positive number is refused by name."""
    from omegaconf import OmegaConf

    from torchrl_wbrm.tasks import EnvConfig
    from torchrl_wbrm.tasks import get_task

    data = LQRDataConfig(behaviour_episodes=400, expert_episodes=200, parallel_envs=200, behaviour_initial_std=3.0)
    shifted, plain = make_lqr_datasets("exp1", data, seed=0), make_lqr_datasets("exp1", SMALL, seed=0)

    def start_std(buffer):
        td = buffer[:]
        return td["observation"][td["step_count"].squeeze(-1) == 0].std().item()

    assert abs(start_std(shifted.transitions) - 3.0) < 0.25
    assert abs(start_std(shifted.expert_samples) - 1.0) < 0.15 and abs(start_std(plain.transitions) - 1.0) < 0.2
    assert shifted.metadata["optimal_return"] == pytest.approx(plain.metadata["optimal_return"])
    assert shifted.metadata["data_config"]["behaviour_initial_std"] == 3.0

    env = OmegaConf.structured(EnvConfig)
    env.lqr_data.behaviour_initial_std = 3.0
    task = get_task(env)
    task.validate()
    eval_cfg = OmegaConf.create({"q_samples": 2000, "seed": 0})
    samples = task.evaluator(eval_cfg).eval_samples
    scale = {name: samples[name]["observation"].pow(2).mean().sqrt().item() for name in ("expert", "behaviour")}
    assert scale["behaviour"] > 1.5 * scale["expert"], scale
    for bad in (0.0, -1.0, float("nan")):
        env.lqr_data.behaviour_initial_std = bad
        with pytest.raises(ValueError, match="env.lqr_data.behaviour_initial_std"):
            get_task(env).validate()


def test_a_save_never_writes_through_links_planted_under_its_sets_names(tmp_path, lqr_data):
    """A data cache folder from someone else may hold links named like the sets: saving replaces the links with the
    sets and leaves what they pointed to untouched; a second save over the first gives the same data."""
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "keep.txt").write_text("theirs")
    root = tmp_path / "ds"
    root.mkdir()
    for name in ("transitions", "behaviour_samples", "expert_samples"):
        (root / name).symlink_to(outside, target_is_directory=True)
    lqr_data.save(root)
    assert sorted(p.name for p in outside.iterdir()) == ["keep.txt"] and (outside / "keep.txt").read_text() == "theirs"
    assert not any((root / name).is_symlink() for name in ("transitions", "behaviour_samples", "expert_samples"))
    lqr_data.save(root)  # over an earlier save
    loaded = OfflineDatasets.load(root)
    assert (loaded.transitions[:]["observation"] == lqr_data.transitions[:]["observation"]).all()
    assert not [p for p in root.iterdir() if p.name.startswith(".")]  # no temporary folder left behind
