"""``ratio.aggregate=episode``: every transition of D gets its episode's weight, the geometric mean of ŵ over the
episode (:func:`~torchrl_wbrm.ratio.weights.episode_weights`), in a run."""
from __future__ import annotations

import math

import pytest
import torch

from torchrl_wbrm.ratio import episode_weights


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", ["flat", "column"])
def test_each_row_gets_the_geometric_mean_of_its_episode(dtype, shape):
    # episode 3: rows 0, 2, 5 (not contiguous); episode 1: rows 1, 3; episode 8: row 4
    w = torch.tensor([2.0, 0.5, 4.0, 8.0, 7.0, 1.0], dtype=dtype)
    episode = torch.tensor([3, 1, 3, 1, 8, 3])
    expected = torch.tensor([2.0, 2.0, 2.0, 2.0, 7.0, 2.0], dtype=torch.float64)  # (2·4·1)^(1/3), (0.5·8)^(1/2), 7
    if shape == "column":
        w, expected = w.reshape(-1, 1), expected.reshape(-1, 1)
    out = episode_weights(w, episode)
    assert out.shape == w.shape and out.dtype == dtype
    torch.testing.assert_close(out.double(), expected, rtol=1e-6, atol=0.0)
    for e in episode.unique():  # constant within an episode
        assert out.reshape(-1)[episode == e].unique().numel() == 1


def test_an_episode_weight_is_exp_of_the_mean_log_and_zero_makes_it_zero():
    w = torch.tensor([[3.0], [5.0], [0.0], [9.0]])
    out = episode_weights(w, torch.tensor([[0], [0], [1], [1]]))
    assert out[0].item() == pytest.approx(math.exp((math.log(3) + math.log(5)) / 2))
    assert out[2].item() == out[3].item() == 0.0


def test_bad_inputs_are_refused():
    with pytest.raises(ValueError, match="one episode id per row"):
        episode_weights(torch.ones(4, 1), torch.zeros(3, dtype=torch.long))
    with pytest.raises(ValueError, match="one weight per row"):
        episode_weights(torch.ones(4, 2), torch.zeros(4, dtype=torch.long))
    with pytest.raises(ValueError, match="finite and non-negative"):
        episode_weights(torch.tensor([1.0, -1.0]), torch.zeros(2, dtype=torch.long))


def test_the_setting_is_validated():
    from torchrl_wbrm.training import WBRMConfig
    from torchrl_wbrm.training.config import validate_config

    cfg = WBRMConfig()
    assert cfg.ratio.aggregate == "transition"
    cfg.ratio.aggregate = "trajectory"
    with pytest.raises(ValueError, match=r"ratio.aggregate='trajectory' is not allowed: choose one of \['transition', "
                                         r"'episode'\]"):
        validate_config(cfg)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from torchrl_wbrm.data.benchmark import make_benchmark_task

    path = tmp_path_factory.mktemp("episode_weights")
    row = make_benchmark_task("pendulum", path, expert_episodes=2, behaviour_episodes=10, reference_episodes=2,
                              few_demonstrations=False)
    return path, row


def _config(data, **overrides):
    from torchrl_wbrm.tasks import EnvConfig
    from torchrl_wbrm.data.minari_data import MinariDataConfig
    from torchrl_wbrm.training import WBRMConfig

    path, row = data
    minari = MinariDataConfig(expert=row["expert"], behaviour=row["behaviour"], data_path=str(path))
    cfg = WBRMConfig(env=EnvConfig(name="minari", kind="minari", minari=minari), plots=False, threads=1, **overrides)
    cfg.ratio.aggregate = "episode"
    cfg.ratio.steps, cfg.ratio.eval_every = 20, 10
    cfg.q.steps, cfg.q.eval_every, cfg.eval.episodes, cfg.eval.train_episodes = 2, 2, 1, 1
    return cfg


def _check_stored(trainer):
    """The weights stored over D: constant within each episode, exp(mean log ŵ) up to the shaping (tempered and
    self-normalised), and not all equal (the episodes differ)."""
    d = trainer.q_buffer.storage[:]
    stored, episode = d["density_ratio"].reshape(-1).double(), d["episode"].reshape(-1)
    raw = trainer.ratio_network(d.select("observation", "action").clone())["density_ratio"].reshape(-1).double()
    per_episode = []
    for e in episode.unique():
        rows = episode == e
        assert torch.allclose(stored[rows], stored[rows][0].expand(int(rows.sum())), rtol=1e-5)
        per_episode.append((stored[rows][0], raw[rows].log().mean().exp(), int(rows.sum())))
    values = torch.stack([v for v, _, _ in per_episode])
    expected = torch.stack([g for _, g, _ in per_episode]).pow(trainer.cfg.ratio.temper)
    counts = torch.tensor([c for _, _, c in per_episode], dtype=torch.float64)
    expected = expected / (expected * counts).sum() * counts.sum()  # self-normalised over D's rows
    torch.testing.assert_close(values, expected, rtol=1e-4, atol=1e-6)
    assert values.max() > values.min()


def test_a_run_stores_each_episodes_weight(data, tmp_path):
    from torchrl_wbrm.training import WBRMTrainer

    trainer = WBRMTrainer(_config(data), tmp_path / "run", progress=False)
    trainer.run()
    _check_stored(trainer)
