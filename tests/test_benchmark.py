"""The locally made benchmark (``torchrl_wbrm.data.benchmark``): one call writes a task's expert and behaviour Minari
datasets with their reference scores, and the few-demonstration sets (the expert pool, the behaviour sets with 5%,
10% and 20% expert episodes, the medium set); the same seed gives the same data, an existing id is refused before any
collecting, a run draws its few expert episodes from the pool by its seed, and a run on them reports D4RL's
normalised score and flags a policy worse than its data."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from torchrl_wbrm.data.benchmark import (
    BENCHMARK_TASKS,
    EXPERT_EVERY,
    EXPERT_SHARES,
    benchmark_table,
    expert_episode_indices,
    few_demonstration_ids,
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
    row = make_benchmark_task("pendulum", path, expert_episodes=3, behaviour_episodes=20, reference_episodes=4)
    return path, row


def _load(path, dataset_id):
    import minari

    from torchrl_wbrm.data.minari_data import _minari_path, minari_data_root

    with _minari_path(minari_data_root(path)):
        return minari.load_dataset(dataset_id)


def test_a_task_writes_both_datasets_with_reference_scores(pendulum):
    import minari

    from torchrl_wbrm.data.minari_data import _minari_path, minari_data_root

    path, row = pendulum
    assert row["expert"] == "benchmark/pendulum/expert-v0" and row["behaviour"] == "benchmark/pendulum/behaviour-v0"
    with _minari_path(minari_data_root(path)):
        expert, behaviour = minari.load_dataset(row["expert"]), minari.load_dataset(row["behaviour"])
    assert expert.total_episodes == 3 and behaviour.total_episodes == 20
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
    """The same seed writes the same files, and expert-v0 / behaviour-v0 do not depend on the few-demonstration sets
    (written here without them: the same bytes)."""
    import hashlib

    from torchrl_wbrm.data.minari_data import minari_data_root

    path, row = pendulum
    again = make_benchmark_task("pendulum", tmp_path, expert_episodes=3, behaviour_episodes=20, reference_episodes=4,
                                few_demonstrations=False)
    for key in ("ref_min_score", "ref_max_score", "behaviour_return_mean", "expert_return_mean"):
        assert again[key] == row[key], key
    assert "expert_pool" not in again and [d["id"] for d in again["datasets"]] == [row["expert"], row["behaviour"]]

    def digest(root, dataset_id):
        return hashlib.sha256((minari_data_root(root) / dataset_id / "data" / "main_data.hdf5").read_bytes()).digest()

    for kind in ("expert", "behaviour"):
        assert digest(tmp_path, row[kind]) == digest(path, row[kind]), kind
    import torchrl_wbrm.data.benchmark as benchmark

    def no_collecting(*args, **kwargs):
        raise AssertionError("collected before refusing")

    monkeypatch.setattr(benchmark, "collect_gym_episodes", no_collecting)
    with pytest.raises(FileExistsError, match="benchmark/pendulum/expert-v0.*--overwrite"):
        make_benchmark_task("pendulum", tmp_path, expert_episodes=3, behaviour_episodes=10)
    (minari_data_root(tmp_path / "pool_only") / few_demonstration_ids("pendulum")["expert_pool"]).mkdir(parents=True)
    with pytest.raises(FileExistsError, match="benchmark/pendulum/expert-pool-v0.*--overwrite"):
        make_benchmark_task("pendulum", tmp_path / "pool_only", expert_episodes=3, behaviour_episodes=10)
    with pytest.raises(ValueError, match="Unknown benchmark task 'hopper'"):
        make_benchmark(tmp_path, tasks=["hopper"])


def test_the_few_demonstration_sets_exist_with_their_expert_share(pendulum):
    """The pool holds twice the expert dataset's episodes, all the expert's; behaviour-expert<pp>-v0 holds pp% expert
    episodes (the ones expert_episode_indices names, whose returns beat every random one's), the rest random; in
    medium-v0 about half the steps are the expert's; the make-up is in the row and the table."""
    path, row = pendulum
    ids = few_demonstration_ids("pendulum")
    assert ids == {"expert_pool": "benchmark/pendulum/expert-pool-v0",
                   "behaviour_expert05": "benchmark/pendulum/behaviour-expert05-v0",
                   "behaviour_expert10": "benchmark/pendulum/behaviour-expert10-v0",
                   "behaviour_expert20": "benchmark/pendulum/behaviour-expert20-v0",
                   "medium": "benchmark/pendulum/medium-v0"}
    made = {d["id"]: d for d in row["datasets"]}
    assert set(made) == {row["expert"], row["behaviour"], *ids.values()}
    pool = _load(path, ids["expert_pool"])
    assert pool.total_episodes == 6 and made[ids["expert_pool"]]["expert_episodes"] == 6
    assert min(float(ep.rewards.sum()) for ep in pool.iterate_episodes()) > row["random_return_mean"]
    for name, share in EXPERT_SHARES.items():
        dataset_id = f"benchmark/pendulum/{name}"
        ds = _load(path, dataset_id)
        assert ds.total_episodes == 20
        chosen = expert_episode_indices(20, share)
        assert len(chosen) == made[dataset_id]["expert_episodes"] == round(share * 20)
        assert made[dataset_id]["expert_transitions"] == 200 * len(chosen)
        returns = [float(ep.rewards.sum()) for ep in ds.iterate_episodes()]
        assert min(returns[i] for i in chosen) > max(r for i, r in enumerate(returns) if i not in chosen), name
    assert expert_episode_indices(300, 0.05) == list(range(19, 300, 20))
    assert expert_episode_indices(300, 0.20) == [i for i in range(300) if i % EXPERT_EVERY == EXPERT_EVERY - 1]
    medium = made[ids["medium"]]
    assert medium["episodes"] == 20 and medium["expert_episodes"] is None
    assert 0.4 < medium["expert_transitions"] / medium["transitions"] < 0.6
    assert row["random_return_mean"] < medium["return_mean"]
    table = benchmark_table([row])
    assert "| benchmark/pendulum/behaviour-expert10-v0 | 20 | 2 | 4,000 | 400 (10%) |" in table


def test_a_run_draws_its_few_expert_episodes_by_its_seed(pendulum):
    """env.minari.expert_episodes=2: S^e is two of the pool's six episodes, the same two for one seed, others for
    other seeds; more than the pool holds is refused in one line naming the key and the count."""
    from torchrl_wbrm.data.minari_data import MinariDataConfig, check_minari_data, make_minari_datasets
    from torchrl_wbrm.tasks import MinariTask

    path, row = pendulum
    config = MinariDataConfig(expert=row["expert_pool"], behaviour=row["behaviour_expert10"], data_path=str(path),
                              expert_episodes=2)
    check_minari_data(config)

    def drawn(seed):
        datasets = make_minari_datasets(config, seed=seed)
        ids = datasets.metadata["expert_episode_ids"]
        assert torch.unique(datasets.expert_samples[:]["episode"]).tolist() == ids
        assert datasets.sizes()["expert_samples"] == 400 and datasets.metadata["expert_dataset_episodes"] == 6
        return ids

    draws = {seed: drawn(seed) for seed in range(5)}
    assert all(len(ids) == 2 for ids in draws.values())
    assert drawn(3) == draws[3]
    assert len({tuple(ids) for ids in draws.values()}) > 1
    config.expert_episodes = None  # all of them
    assert make_minari_datasets(config, seed=0).sizes()["expert_samples"] == 6 * 200
    config.expert_episodes = 7
    with pytest.raises(ValueError, match=r"env.minari.expert_episodes=7 but the Minari expert dataset "
                                         r"'benchmark/pendulum/expert-pool-v0' holds 6 episode\(s\)"):
        check_minari_data(config)
    with pytest.raises(ValueError, match=r"env.minari.expert_episodes=7 .* holds 6"):
        make_minari_datasets(config, seed=0)
    from torchrl_wbrm.tasks import EnvConfig

    config.expert_episodes = 0
    with pytest.raises(ValueError, match="env.minari.expert_episodes must be >= 1"):
        MinariTask(EnvConfig(name="minari", kind="minari", minari=config)).validate()


@pytest.mark.slow
def test_a_run_reports_the_normalised_score_and_flags_a_policy_below_its_data(pendulum, tmp_path):
    """A run of a few steps on the benchmark's Pendulum data: its results carry the normalised score on D4RL's scale
    and, its policy being no better than random torques, the below_behaviour flag with its figures; given an earlier
    evaluation at the expert's return, the return_fell flag too."""
    from torchrl_wbrm.training import WBRMConfig, WBRMTrainer
    from torchrl_wbrm.tasks import EnvConfig
    from torchrl_wbrm.data.minari_data import MinariDataConfig

    path, row = pendulum
    minari = MinariDataConfig(expert=row["expert"], behaviour=row["behaviour"], data_path=str(path))
    cfg = WBRMConfig(env=EnvConfig(name="minari", kind="minari", minari=minari), algo="brm", plots=False, threads=1)
    cfg.q.steps, cfg.q.eval_every, cfg.eval.episodes, cfg.eval.train_episodes = 2, 2, 3, 1
    trainer = WBRMTrainer(cfg, tmp_path / "run", progress=False)
    results = trainer.run()
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
    assert "return_fell" not in results["flags"] and not results["return_check"]["fell"]  # one evaluation only
    # return_fell, checked over the trainer's own evaluations: as if step 1 had scored the expert's return
    trainer.history.insert(0, _evaluation(1, row["expert_return_mean"], 1.0))
    results = trainer.results()
    check = results["return_check"]
    assert "return_fell" in results["flags"] and (check["best_step"], check["step"], check["return"]) == (1, 2, final["return"])
    saved = json.loads((tmp_path / "run" / "results.json").read_text())
    assert "return_fell" in saved["flags"] and "FLAG return_fell" in summarise(saved)


def _evaluation(step, ret, ci):
    return {"stage": "q", "step": step, "return": ret, "return_ci": ci}


def test_return_fell_needs_disjoint_intervals_and_a_material_fall():
    """The ``return_fell`` rule (:func:`~torchrl_wbrm.training.reporting.return_fell`), behaviour data at -100: the
    best earlier evaluation 200 ± 10 (a gain of 300 over the data), so a quarter of the gain is 75."""
    from torchrl_wbrm.training.reporting import RETURN_FALL_FRACTION, return_fell

    assert RETURN_FALL_FRACTION == 0.25
    data = {"behaviour_mean_return": -100.0}
    history = [_evaluation(500, 150.0, 5.0), _evaluation(1000, 200.0, 10.0),
               {"stage": "q_train", "step": 1000, "return": -1e9}]  # training records are not evaluations
    check = return_fell([*history, _evaluation(1500, 100.0, 20.0)], data)
    assert check["fell"] and (check["best_step"], check["best_return"], check["step"]) == (1000, 200.0, 1500)
    assert not return_fell([*history, _evaluation(1500, 130.0, 70.0)], data)["fell"]  # the intervals overlap
    assert not return_fell([*history, _evaluation(1500, 130.0, 1.0)], data)["fell"]  # disjoint, but 70 < 75
    assert return_fell([*history, _evaluation(1500, 124.0, 1.0)], data)["fell"]  # 76 >= 75
    assert not return_fell([*history, _evaluation(1500, 250.0, 1.0)], data)["fell"]  # it rose
    assert not return_fell([*history, _evaluation(1500, 100.0, 20.0)], {})["fell"]  # no behaviour return (LQR)
    assert not return_fell([*history, _evaluation(1500, float("nan"), 20.0)], data)["fell"]
    assert not return_fell([_evaluation(1500, -1e9, 1.0)], data)["fell"]  # one evaluation
    # below the data from the start: no gain over it to lose
    assert not return_fell([_evaluation(500, -150.0, 1.0), _evaluation(1000, -300.0, 1.0)], data)["fell"]


@pytest.mark.slow
def test_benchmark_tables_quick_writes_the_table(tmp_path):
    """``recipes/benchmark_tables.py --quick``: the datasets are made when missing, every (task, algo, seed) runs the
    recipe with the dataset keys only (and ``--overrides``), and tables.md has one row per cell with the normalised
    score; a malformed override is refused before anything runs."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "recipes" / "benchmark_tables.py"
    spec = importlib.util.spec_from_file_location("benchmark_tables", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    args = ["--quick", "--tasks", "pendulum", "--algos", "wbrm", "bc", "--seeds", "1", "--jobs", "1",
            "--data-path", str(tmp_path / "data"), "--out", str(tmp_path / "out")]
    for bad in ("q.layer_norm", "q.steps=3e3"):
        with pytest.raises(SystemExit):
            module.main([*args, "--overrides", bad])
    assert not (tmp_path / "out").exists()
    module.main([*args, "--overrides", "q.layer_norm=false"])
    table = (tmp_path / "out" / "tables.md").read_text()
    rows = [line for line in table.splitlines() if line.startswith("| pendulum |")]
    assert [row.split(" | ")[1] for row in rows] == ["bc", "wbrm"]
    for row in rows:
        cells = row.split(" | ")
        assert cells[3] == "1" and float(cells[4]) == float(cells[4])  # one seed, a finite normalised score
    results = json.loads(next((tmp_path / "out").rglob("wbrm/*/seed0/results.json")).read_text())
    assert results["config"]["q"]["layer_norm"] is False  # the override, against the continuous-action default
    assert "env.minari.expert=benchmark/pendulum/expert-v0" not in str(results["config"])  # resolved config saved
    assert results["config"]["env"]["minari"]["expert"] == "benchmark/pendulum/expert-v0"
    assert results["config"]["q"]["expert_bc_alpha"] in (0.0, 1.0)


def test_the_behaviour_sets_say_which_episodes_are_the_experts(pendulum):
    """Each dataset's metadata names its expert episodes (Minari ids, as D's "episode"), and a run's data carry them
    (``baselines.bc.data=oracle`` clones those); a dataset that does not say gives None."""
    from torchrl_wbrm.data.minari_data import MinariDataConfig, make_minari_datasets

    path, row = pendulum
    for name, share in EXPERT_SHARES.items():
        ds = _load(path, f"benchmark/pendulum/{name}")
        assert ds.storage.metadata["expert_episode_ids"] == expert_episode_indices(20, share)
    assert _load(path, row["behaviour"]).storage.metadata["expert_episode_ids"] == [4, 9, 14, 19]
    assert _load(path, row["medium"]).storage.metadata["expert_episode_ids"] == []
    config = MinariDataConfig(expert=row["expert_pool"], behaviour=row["behaviour_expert10"], data_path=str(path),
                              expert_episodes=1)
    datasets = make_minari_datasets(config, seed=0)
    assert datasets.metadata["behaviour_expert_episode_ids"] == [9, 19]
    meta = path / "benchmark" / "pendulum" / "behaviour-expert10-v0" / "data" / "metadata.json"
    saved = json.loads(meta.read_text())
    meta.write_text(json.dumps({k: v for k, v in saved.items() if k != "expert_episode_ids"}))
    try:
        assert make_minari_datasets(config, seed=0).metadata["behaviour_expert_episode_ids"] is None
    finally:
        meta.write_text(json.dumps(saved))


def test_few_demonstration_table_quick(pendulum, tmp_path):
    """``recipes/benchmark_tables.py --few-demonstrations --quick`` on the fixture's data: one row per method of the
    cell (S^e one pool episode, D the 10% set); the ŵ-weighted cloning fits stage 1, the oracle clones D's expert
    episodes with S^e; an unknown method is refused naming the choices."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "recipes" / "benchmark_tables.py"
    spec = importlib.util.spec_from_file_location("benchmark_tables", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    args = ["--quick", "--few-demonstrations", "--tasks", "pendulum", "--expert-episodes", "1", "--seeds", "1",
            "--jobs", "1", "--data-path", str(pendulum[0]), "--out", str(tmp_path / "out")]
    with pytest.raises(ValueError, match="--methods sac: not a method of the few-demonstration table"):
        module.main([*args, "--methods", "sac"])
    module.main([*args, "--methods", "bc_weighted", "bc_expert_like", "bc_oracle"])
    table = (tmp_path / "out" / "tables.md").read_text()
    rows = [line.split(" | ") for line in table.splitlines() if line.startswith("| pendulum |")]
    assert [(r[1], r[2], r[3]) for r in rows] == [("se1_expert10", "bc_weighted", "1"),
                                                  ("se1_expert10", "bc_expert_like", "1"),
                                                  ("se1_expert10", "bc_oracle", "1")]
    png = tmp_path / "out" / "few_demonstrations.png"  # the score against S^e's size, a line per method
    assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert all(float(r[4]) == float(r[4]) for r in rows)  # a finite normalised score
    out = tmp_path / "out" / "pendulum" / "se1_expert10"
    weighted = json.loads((out / "bc_weighted" / "seed0" / "results.json").read_text())
    assert weighted["ratio"]["source"] == "learned" and weighted["ratio"]["steps_run"] > 0
    expert_like = json.loads((out / "bc_expert_like" / "seed0" / "results.json").read_text())
    assert expert_like["ratio"]["source"] == "learned" and "expert_like_episodes" in expert_like["weights"]
    oracle = json.loads((out / "bc_oracle" / "seed0" / "results.json").read_text())
    assert oracle["ratio"]["source"] == "none" and oracle["config"]["baselines"]["bc"]["data"] == "oracle"


def test_few_demonstration_cells_at_other_budgets():
    """``--budgets`` in the few-demonstration table: each budget beyond the default is a cell of its own, labelled
    ``_x<k>``, with ``k`` times the default ``q.steps`` and ``q.eval_every`` after the method's overrides."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "recipes" / "benchmark_tables.py"
    spec = importlib.util.spec_from_file_location("benchmark_tables", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    cells = module.few_demonstration_cells(["pendulum"], [3], ["10"], ["wbrm_from_d", "brm"], Path("/data"),
                                           "benchmark", (1, 3), 3000, 500)
    assert [(c["cell"], c["method"]) for c in cells] == [
        ("se3_expert10", "wbrm_from_d"), ("se3_expert10", "brm"),
        ("se3_expert10_x3", "wbrm_from_d"), ("se3_expert10_x3", "brm")]
    assert cells[0]["overrides"][-2:] == ["algo=wbrm", "q.expert_bc_from_d=true"]
    assert cells[2]["overrides"][-4:] == ["algo=wbrm", "q.expert_bc_from_d=true", "q.steps=9000", "q.eval_every=1500"]
    assert not any(o.startswith("q.steps=") for o in cells[1]["overrides"])
    # the medium set: D from medium-v0, labelled se<n>_medium; the oracle has no expert episodes there to clone
    medium = module.few_demonstration_cells(["pendulum"], [3], ["medium"], ["brm"], Path("/data"), "benchmark")
    assert [c["cell"] for c in medium] == ["se3_medium"]
    assert "env.minari.behaviour=benchmark/pendulum/medium-v0" in medium[0]["overrides"]
    with pytest.raises(ValueError, match="medium-v0 has no expert episodes"):
        module.few_demonstration_cells(["pendulum"], [3], ["medium"], ["bc_oracle"], Path("/data"), "benchmark")


def test_few_demonstration_cells_of_a_locomotion_task():
    """A locomotion task's D is its ``random-expert<pp>-v0`` set (any two-digit share); a small task's share it does
    not have is refused naming the set."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "recipes" / "benchmark_tables.py"
    spec = importlib.util.spec_from_file_location("benchmark_tables", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    cells = module.few_demonstration_cells(["hopper"], [1, 5], ["05", "01"], ["wbrm"], Path("/data"), "benchmark")
    assert [c["cell"] for c in cells] == ["se1_expert05", "se1_expert01", "se5_expert05", "se5_expert01"]
    assert "env.minari.behaviour=benchmark/hopper/random-expert05-v0" in cells[0]["overrides"]
    assert "env.minari.expert=benchmark/hopper/expert-pool-v0" in cells[0]["overrides"]
    assert "env.minari.expert_episodes=5" in cells[2]["overrides"]
    with pytest.raises(ValueError, match="no behaviour-expert01-v0 set"):
        module.few_demonstration_cells(["pendulum"], [3], ["01"], ["wbrm"], Path("/data"), "benchmark")


def test_missing_locomotion_datasets_are_refused_naming_the_command(tmp_path, capsys):
    """A locomotion task whose datasets are not under ``--data-path`` is refused in one line naming the path and the
    command that makes them; nothing is made or run."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "recipes" / "benchmark_tables.py"
    spec = importlib.util.spec_from_file_location("benchmark_tables", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    with pytest.raises(SystemExit):
        module.main(["--few-demonstrations", "--tasks", "walker2d", "--expert-shares", "05", "--data-path",
                     str(tmp_path), "--out", str(tmp_path / "out"), "--docs-dir", "none"])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"--data-path {tmp_path}" in err and "benchmark/walker2d/expert-pool-v0" in err
    assert "python -m torchrl_wbrm.data.benchmark" in err and "--tasks walker2d" in err
    assert list(tmp_path.iterdir()) == []


def test_the_share_plot_draws_a_line_per_method_against_the_expert_share(tmp_path):
    """``expert_share.png``: a panel per (task, S^e size), the expert's share of D on x, a line per method; the
    medium cells are left out of it, each line holds the seeds' mean, and an S^e size with runs at one share only
    gets no panel."""
    import importlib.util
    import json
    from pathlib import Path

    import matplotlib

    matplotlib.use("Agg")
    path = Path(__file__).resolve().parents[1] / "recipes" / "benchmark_tables.py"
    spec = importlib.util.spec_from_file_location("benchmark_tables", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    scores = {("se5_expert01", "wbrm"): [10.0, 20.0], ("se5_expert05", "wbrm"): [50.0, 70.0],
              ("se5_expert05", "bc"): [30.0, 30.0], ("se5_medium", "bc"): [5.0, 5.0],
              ("se1_expert05", "brm"): [40.0, 40.0]}
    for (cell, method), values in scores.items():
        for seed, score in enumerate(values):
            run = tmp_path / cell / method / f"seed{seed}"
            run.mkdir(parents=True)
            (run / "results.json").write_text(json.dumps({
                "status": "finished", "seed": seed, "final": {"normalised_score": score},
                "study": {"task": "hopper", "cell": cell, "method": method}}))
    drawn = {}
    import matplotlib.axes

    original = matplotlib.axes.Axes.errorbar

    def spy(self, x, y, *args, **kwargs):
        drawn[kwargs["label"].split()[0]] = (list(x), list(y))
        return original(self, x, y, *args, **kwargs)

    matplotlib.axes.Axes.errorbar = spy
    try:
        figure = module.few_demonstrations_plot(tmp_path, "share")
    finally:
        matplotlib.axes.Axes.errorbar = original
    assert figure is not None and Path(figure).name == "expert_share.png" and Path(figure).is_file()
    assert drawn == {"wbrm": ([1, 5], [15.0, 60.0]), "bc": ([5], [30.0])}
    with pytest.raises(ValueError, match="against="):
        module.few_demonstrations_plot(tmp_path, "size")


def test_the_few_demonstration_report_gives_paired_differences_over_shared_seeds():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "recipes" / "benchmark_tables.py"
    spec = importlib.util.spec_from_file_location("benchmark_tables", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)

    def runs(*scores):
        return [{"seed": s, "final": {"normalised_score": v}} for s, v in scores]

    rows = {("hopper", "se5_expert05", "wbrm"): runs((0, 30.0), (1, 20.0), (2, 34.0)),
            ("hopper", "se5_expert05", "brm"): runs((0, 33.0), (1, 33.0)),  # seed 2 missing: not paired
            ("hopper", "se5_expert05", "bc"): runs((5, 34.0))}             # no shared seed with either
    lines = module.paired_differences(rows)
    assert lines[2] == "| hopper | se5_expert05 | wbrm − brm | 2 | -8.0 ± 63.5 | 0: -3.0, 1: -13.0 |"
    assert len(lines) == 3 and module.paired_differences({}) == []
