"""The locally made benchmark (``torchrl_wbrm.data.benchmark``): one call writes a task's expert and behaviour Minari
datasets with their reference scores, the same seed gives the same data, an existing id is refused before any
collecting, and a run on them reports D4RL's normalised score and flags a policy worse than its data."""
from __future__ import annotations

import json

import numpy as np
import pytest

from torchrl_wbrm.data.benchmark import (
    BENCHMARK_TASKS,
    EXPERT_EVERY,
    benchmark_table,
    make_benchmark,
    make_benchmark_task,
    normalised_score,
)


def test_normalised_score_is_d4rls():
    assert normalised_score(-100.0, -200.0, 0.0) == pytest.approx(50.0)
    np.testing.assert_allclose(normalised_score([-200.0, 0.0], -200.0, 0.0), [0.0, 100.0])
    with pytest.raises(ValueError, match="ref_max > ref_min"):
        normalised_score(1.0, 2.0, 2.0)


def test_the_tasks_differ_in_horizon_reward_and_termination():
    import gymnasium as gym

    assert {"pendulum", "mountain_car", "lunar_lander", "inverted_pendulum"} <= set(BENCHMARK_TASKS)
    horizons = {gym.spec(t.env_id).max_episode_steps for t in BENCHMARK_TASKS.values()}
    assert len(horizons) >= 2


@pytest.fixture(scope="module")
def pendulum(tmp_path_factory):
    path = tmp_path_factory.mktemp("bench")
    row = make_benchmark_task("pendulum", path, expert_episodes=3, behaviour_episodes=10, reference_episodes=4)
    return path, row


def test_a_task_writes_both_datasets_with_reference_scores(pendulum):
    import minari

    from torchrl_wbrm.data.minari_data import _minari_path, minari_data_root

    path, row = pendulum
    assert row["expert"] == "benchmark/pendulum/expert-v0" and row["behaviour"] == "benchmark/pendulum/behaviour-v0"
    with _minari_path(minari_data_root(path)):
        expert, behaviour = minari.load_dataset(row["expert"]), minari.load_dataset(row["behaviour"])
    assert expert.total_episodes == 3 and behaviour.total_episodes == 10
    for ds in (expert, behaviour):
        assert ds.storage.metadata["ref_min_score"] == pytest.approx(row["ref_min_score"])
        assert ds.storage.metadata["ref_max_score"] == pytest.approx(row["ref_max_score"])
    # the swing-up expert beats random torques by far; the behaviour mixes them (every fifth episode the expert's)
    assert row["ref_max_score"] > row["ref_min_score"] + 500
    assert row["random_return_mean"] < row["behaviour_return_mean"] < row["expert_return_mean"]
    returns = [float(ep.rewards.sum()) for ep in behaviour.iterate_episodes()]
    expert_like = [r for i, r in enumerate(returns) if i % EXPERT_EVERY == EXPERT_EVERY - 1]
    assert min(expert_like) > max(r for i, r in enumerate(returns) if i % EXPERT_EVERY != EXPERT_EVERY - 1)
    assert "| pendulum | Pendulum-v1 |" in benchmark_table([row])


def test_same_seed_same_data_and_existing_ids_are_refused_first(pendulum, tmp_path, monkeypatch):
    path, row = pendulum
    again = make_benchmark_task("pendulum", tmp_path, expert_episodes=3, behaviour_episodes=10, reference_episodes=4)
    for key in ("ref_min_score", "ref_max_score", "behaviour_return_mean", "expert_return_mean"):
        assert again[key] == row[key], key
    import torchrl_wbrm.data.benchmark as benchmark

    def no_collecting(*args, **kwargs):
        raise AssertionError("collected before refusing")

    monkeypatch.setattr(benchmark, "collect_gym_episodes", no_collecting)
    with pytest.raises(FileExistsError, match="benchmark/pendulum/expert-v0.*--overwrite"):
        make_benchmark_task("pendulum", tmp_path, expert_episodes=3, behaviour_episodes=10)
    with pytest.raises(ValueError, match="Unknown benchmark task 'hopper'"):
        make_benchmark(tmp_path, tasks=["hopper"])


@pytest.mark.slow
def test_a_run_reports_the_normalised_score_and_flags_a_policy_below_its_data(pendulum, tmp_path):
    """A run of a few steps on the benchmark's Pendulum data: its results carry the normalised score on D4RL's scale
    and, its policy being no better than random torques, the below_behaviour flag with its figures."""
    from torchrl_wbrm.training import WBRMConfig, WBRMTrainer
    from torchrl_wbrm.data import EnvConfig
    from torchrl_wbrm.data.minari_data import MinariDataConfig

    path, row = pendulum
    minari = MinariDataConfig(expert=row["expert"], behaviour=row["behaviour"], data_path=str(path))
    cfg = WBRMConfig(env=EnvConfig(name="minari", kind="minari", minari=minari), algo="brm", plots=False, threads=1)
    cfg.q.steps, cfg.q.eval_every, cfg.eval.episodes, cfg.eval.train_episodes = 2, 2, 3, 1
    results = WBRMTrainer(cfg, tmp_path / "run", progress=False).run()
    final = results["final"]
    expected = normalised_score(final["return"], row["ref_min_score"], row["ref_max_score"])
    assert final["normalised_score"] == pytest.approx(float(expected))
    assert results["behaviour_check"]["behaviour_mean_return"] == pytest.approx(row["behaviour_return_mean"], rel=1e-5)
    assert final["return"] < row["behaviour_return_mean"]  # two updates: no better than random torques
    assert "below_behaviour" in results["flags"]
    saved = json.loads((tmp_path / "run" / "results.json").read_text())
    assert "below_behaviour" in saved["flags"]
    from torchrl_wbrm.training.reporting import summarise

    text = summarise(saved)
    assert "FLAG below_behaviour" in text and "normalised score" in text


@pytest.mark.slow
def test_benchmark_tables_quick_writes_the_table(tmp_path):
    """``recipes/benchmark_tables.py --quick``: the datasets are made when missing, every (task, algo, seed) runs the
    recipe with the dataset keys only, and tables.md has one row per cell with the normalised score."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "recipes" / "benchmark_tables.py"
    spec = importlib.util.spec_from_file_location("benchmark_tables", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.main(["--quick", "--tasks", "pendulum", "--algos", "wbrm", "bc", "--seeds", "1", "--jobs", "1",
                 "--data-path", str(tmp_path / "data"), "--out", str(tmp_path / "out")])
    table = (tmp_path / "out" / "tables.md").read_text()
    rows = [line for line in table.splitlines() if line.startswith("| pendulum |")]
    assert [row.split(" | ")[1] for row in rows] == ["bc", "wbrm"]
    for row in rows:
        cells = row.split(" | ")
        assert cells[3] == "1" and float(cells[4]) == float(cells[4])  # one seed, a finite normalised score
    results = json.loads(next((tmp_path / "out").rglob("results.json")).read_text())
    assert "env.minari.expert=benchmark/pendulum/expert-v0" not in str(results["config"])  # resolved config saved
    assert results["config"]["env"]["minari"]["expert"] == "benchmark/pendulum/expert-v0"
    assert results["config"]["q"]["expert_bc_alpha"] in (0.0, 1.0)
