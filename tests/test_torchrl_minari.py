"""torchrl_wbrm.data.torchrl_minari: a local Minari dataset as a torchrl replay buffer in MinariExperienceReplay's
layout, compared value by value with minari.load_dataset on datasets written in the test; and a record of torchrl's own
reader, which reads zeros."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchrl_wbrm.data import write_minari_dataset
from torchrl_wbrm.data.minari_examples import collect_gym_episodes
from torchrl_wbrm.data.torchrl_minari import minari_replay_buffer, read_minari_as_torchrl


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    folder = tmp_path_factory.mktemp("minari")
    cartpole = collect_gym_episodes("CartPole-v1", lambda obs, rng: int(rng.integers(0, 2)), 3, seed=0)
    pendulum = collect_gym_episodes("Pendulum-v1", lambda obs, rng: rng.uniform(-2, 2, 1).astype(np.float32), 2, seed=0)
    write_minari_dataset("test/cartpole-v0", cartpole, data_path=folder, env="CartPole-v1")
    write_minari_dataset("test/pendulum-v0", pendulum, data_path=folder, env="Pendulum-v1")
    return folder


@pytest.mark.parametrize("dataset_id", ["test/cartpole-v0", "test/pendulum-v0"])
def test_the_buffer_holds_minari_s_own_values_in_torchrl_s_layout(datasets, dataset_id, monkeypatch):
    import minari

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(datasets))
    reference = minari.load_dataset(dataset_id)
    rb = minari_replay_buffer(dataset_id, 4, data_path=datasets)
    data = rb[:]
    episodes = list(reference.iterate_episodes())
    assert len(rb) == sum(len(e.rewards) for e in episodes) and data.batch_size == (len(rb),)
    row = 0
    for episode in sorted(episodes, key=lambda e: e.id):
        steps = len(episode.rewards)
        part = data[row:row + steps]
        row += steps
        torch.testing.assert_close(part["observation"], torch.as_tensor(episode.observations[:-1]))
        torch.testing.assert_close(part["next", "observation"], torch.as_tensor(episode.observations[1:]))
        torch.testing.assert_close(part["action"], torch.as_tensor(np.asarray(episode.actions)))
        torch.testing.assert_close(part["next", "reward"], torch.as_tensor(episode.rewards).reshape(steps, 1))
        terminated = torch.as_tensor(episode.terminations).reshape(steps, 1)
        truncated = torch.as_tensor(episode.truncations).reshape(steps, 1)
        assert torch.equal(part["next", "terminated"], terminated) and torch.equal(part["next", "truncated"], truncated)
        assert torch.equal(part["next", "done"], terminated | truncated)
        assert (part["episode"] == episode.id).all()
    assert data["observation"].abs().sum() > 0 and data["next", "reward"].abs().sum() > 0
    # torchrl's layout: the keys and the shapes of MinariExperienceReplay
    assert set(data.keys(True, True)) == {
        "observation", "action", "episode", ("next", "observation"), ("next", "reward"), ("next", "terminated"),
        ("next", "truncated"), ("next", "done")}
    assert data["next", "reward"].shape[-1] == 1 and data["next", "done"].dtype == torch.bool
    assert rb.sample().batch_size == (4,)
    with pytest.raises(RuntimeError):
        rb.extend(data[:2])  # an immutable dataset, as torchrl's
    with pytest.raises(FileNotFoundError, match="test/missing-v0"):
        read_minari_as_torchrl("test/missing-v0", data_path=datasets)


def test_torchrl_s_own_minari_reader_still_reads_zeros(datasets, tmp_path, monkeypatch):
    """torchrl 0.14.1's MinariExperienceReplay(load_from_local_minari=True) reads every observation, action and reward
    of a local Minari 0.5.4 dataset as 0. When this test fails, torchrl reads them: point the docs to it."""
    from torchrl.data.datasets import MinariExperienceReplay

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(datasets))
    theirs = MinariExperienceReplay("test/pendulum-v0", batch_size=4, download=False, load_from_local_minari=True,
                                    root=str(tmp_path / "torchrl"))[:]
    ours = read_minari_as_torchrl("test/pendulum-v0", data_path=datasets)
    assert theirs.batch_size == ours.batch_size
    # the same keys, shapes and dtypes as torchrl's reader
    assert set(theirs.keys(True, True)) == set(ours.keys(True, True))
    for key in ours.keys(True, True):
        assert (theirs[key].shape, theirs[key].dtype) == (ours[key].shape, ours[key].dtype), key
    assert ours["observation"].abs().sum() > 0
    read_zeros = all(float(theirs[key].abs().sum()) == 0
                     for key in ("observation", "action", ("next", "observation"), ("next", "reward")))
    assert read_zeros, "torchrl's MinariExperienceReplay now reads the values: the docs can point to it"
