"""The trainer's flags and stops: a failed stage 1 is flagged, an interrupt during an evaluation stops at once and resumes exactly,
a saved dataset is never served stale from the data cache, and config and data errors name the key, the dataset and
what is expected (before any data are collected where the config alone tells)."""
from __future__ import annotations

import json
import os
import signal
import time
import warnings

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict

from torchrl_wbrm.data import OfflineDatasets
from torchrl_wbrm.tasks import cached_offline_datasets
from torchrl_wbrm.data.datasets import min_behaviour_episodes
from torchrl_wbrm.tasks import EnvConfig
from tests.references import tiny_lqr_config
from torchrl_wbrm.training import WBRMTrainer
from torchrl_wbrm.training.config import WBRMConfig, validate_config
from torchrl_wbrm.training.stops import RunInterrupted
from torchrl_wbrm.training.reporting import summarise


pytestmark = pytest.mark.usefixtures("single_thread")  # tests/conftest.py: one torch thread per test


def tiny(**overrides) -> WBRMConfig:
    """The tiny LQR run (tests/references.py), with this file's own settings."""
    return tiny_lqr_config({"checkpoint_every": 0}, **overrides)


# ---------------------------------------------------------------------- a failed stage 1
def test_collapsed_stage_1_is_flagged(tmp_path):
    """ratio.lr=1.0: the held-out loss rises from -2 to thousands and never beats the start; the run says so."""
    results = WBRMTrainer(tiny(ratio={"lr": 1.0, "steps": 300, "eval_every": 100}), tmp_path, progress=False).run()
    check = results["ratio"]["check"]
    assert results["status"] == "finished" and "ratio_collapse" in results["flags"]
    assert check["collapse"] and not check["improved"]
    assert check["worst_held_out_loss"] > check["start_held_out_loss"] + 1.0
    assert any("the fit only got worse" in r for r in check["reasons"])
    text = summarise(results)
    assert "FLAG ratio_collapse: stage 1 failed" in text and "lower ratio.lr" in text


def test_healthy_stage_1_is_not_flagged(tmp_path):
    results = WBRMTrainer(tiny(), tmp_path, progress=False).run()
    check = results["ratio"]["check"]
    assert "ratio_collapse" not in results["flags"] and not check["collapse"]
    assert 0.5 < check["mean_behaviour"] < 2.0
    assert check["best_held_out_loss"] < check["start_held_out_loss"]
    assert "ratio_collapse" not in summarise(results)


def test_a_stage_1_that_only_ties_its_start_is_not_flagged(tmp_path):
    """Behaviour data close to the expert's leave nothing to learn: a fit that never beats its start by a hair is
    not a failure (the run is unweighted, as it should be)."""
    trainer = WBRMTrainer(tiny(ratio={"lr": 1e-7}), tmp_path, progress=False)
    results = trainer.run()
    check = results["ratio"]["check"]
    assert abs(check["worst_held_out_loss"] - check["start_held_out_loss"]) < 0.05
    assert "ratio_collapse" not in results["flags"] and not check["collapse"]


def test_stored_ratios_far_from_one_are_flagged(tmp_path):
    trainer = WBRMTrainer(tiny(), tmp_path, progress=False)
    check = trainer.ratio_fitter.verdict(torch.full((100, 1), 1e-3))
    assert check["collapse"] and check["at_lower_bound"] == 1.0
    assert any("the mean of ŵ over D is 0.001" in r for r in check["reasons"])
    assert not trainer.ratio_fitter.verdict(torch.full((100, 1), 1.5))["collapse"]
    trainer.release()


# ---------------------------------------------------------------------- an interrupt during an evaluation
def test_interrupt_during_the_final_evaluation_stops_at_once_and_resumes_exactly(tmp_path):
    cfg = tiny(eval={"episodes": 60, "train_episodes": 20, "q_samples": 300})
    reference = WBRMTrainer(cfg, tmp_path / "whole", progress=False).run()

    trainer = WBRMTrainer(cfg, tmp_path / "cut", progress=False)
    evaluate = trainer.evaluation.evaluator.evaluate

    def long_final_evaluation(policy, *, episodes, **kwargs):
        if episodes == 60:  # the final one: a signal arrives while it runs, which would take a minute
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(60)
        return evaluate(policy, episodes=episodes, **kwargs)

    trainer.evaluation.evaluator.evaluate = long_final_evaluation
    start = time.perf_counter()
    with pytest.raises(RunInterrupted, match=r"SIGINT received: stopped during the evaluation in stage 'q' at step "
                                             r"40, checkpoint written to .*resume=") as err:
        trainer.run()
    assert time.perf_counter() - start < 30 and err.value.during == "evaluation"
    ckpt = torch.load(tmp_path / "cut" / "checkpoint.pt", weights_only=True)
    assert ckpt["state"] == {"stage": "q", "step": 40, "eval_pending": 40}
    assert not (tmp_path / "cut" / "results.json").exists()

    resumed = WBRMTrainer(cfg, tmp_path / "cut", progress=False, resume=True).run()
    assert resumed["final"] == reference["final"] and resumed["final"]["step"] == 40  # evaluated on resume, alike
    history = {name: json.loads((tmp_path / name / "history.json").read_text()) for name in ("whole", "cut")}
    assert history["cut"] == history["whole"]  # every record, in the same order


# ---------------------------------------------------------------------- the data cache and a saved dataset
def _saved(path, seed):
    from torchrl_wbrm.data.lqr import LQRDataConfig, make_lqr_datasets

    make_lqr_datasets("exp1", LQRDataConfig(behaviour_episodes=8, expert_episodes=4, parallel_envs=4),
                      seed=seed).save(path)


def test_data_cache_never_serves_a_saved_dataset_stale(tmp_path):
    data, cache = tmp_path / "ds", tmp_path / "cache"
    _saved(data, seed=0)
    env = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(EnvConfig),
                                              {"lqr_data": {"dataset_dir": str(data)}}))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "failed verification and is rebuilt" warning
        first = cached_offline_datasets(env, seed=0, cache_dir=cache)
        assert torch.equal(first.transitions[:]["observation"], OfflineDatasets.load(data).transitions[:]["observation"])
        import shutil

        shutil.rmtree(data)
        _saved(data, seed=1)  # the dataset is made anew
        second = cached_offline_datasets(env, seed=0, cache_dir=cache)
    assert torch.equal(second.transitions[:]["observation"], OfflineDatasets.load(data).transitions[:]["observation"])
    assert not torch.equal(second.transitions[:]["observation"][:10], first.transitions[:]["observation"][:10])
    assert not cache.exists() or not any(cache.iterdir())  # no second copy of data already on disk


# ---------------------------------------------------------------------- config and data errors
@pytest.mark.parametrize(
    "overrides, named",
    [
        ({"ratio": {"bounds": [0.5]}}, "ratio.bounds must hold two numbers [Φ, Ψ] with 0 < Φ < 1 ≤ Ψ, got [0.5]"),
        ({"ratio": {"bounds": [0.1, 2.0, 3.0]}}, "ratio.bounds must hold two numbers"),
        ({"env": {"lqr_data": {"behaviour_episodes": 2}}}, "env.lqr_data.behaviour_episodes must be >= 4"),
        ({"env": {"lqr_data": {"behaviour_episodes": 3}}}, "env.lqr_data.behaviour_episodes must be >= 4"),
        ({"logger": {"backend": "wandb", "project": "team/project"}}, "logger.project='team/project' is refused by wandb"),
        ({"logger": {"backend": "wandb", "project": "p" * 129}}, "exceeded 128 characters"),
    ],
)
def test_config_errors_name_the_key_before_any_data(tmp_path, overrides, named):
    cfg = tiny(data_cache=str(tmp_path / "cache"), **overrides)
    with pytest.raises(ValueError) as err:
        validate_config(cfg)
    assert named in str(err.value)
    with pytest.raises(ValueError):
        WBRMTrainer(cfg, tmp_path / "run", progress=False)
    assert not (tmp_path / "cache").exists()  # refused before any data were collected


def test_the_smallest_behaviour_data_train():
    assert min_behaviour_episodes(0.5) == 4 and min_behaviour_episodes(0.2) == 3 and min_behaviour_episodes(0.9) >= 4
    validate_config(tiny(env={"lqr_data": {"behaviour_episodes": 4}}))


def _episodes(n: int, steps: int = 5) -> TensorDict:
    rows = n * steps
    return TensorDict({
        "observation": torch.randn(rows, 2), "action": torch.randn(rows, 1),
        "episode": torch.arange(n).repeat_interleave(steps),
        "next": {"observation": torch.randn(rows, 2), "reward": torch.randn(rows, 1),
                 "done": torch.zeros(rows, 1, dtype=torch.bool), "terminated": torch.zeros(rows, 1, dtype=torch.bool),
                 "truncated": torch.zeros(rows, 1, dtype=torch.bool)},
    }, batch_size=[rows])


@pytest.mark.parametrize("episodes", [1, 2, 3])
def test_too_few_behaviour_episodes_name_the_dataset_and_the_minimum(episodes):
    with pytest.raises(ValueError, match=rf"The behaviour dataset 'mc/behaviour-v0' holds {episodes} episode\(s\); "
                                         r"at least 4 are needed"):
        OfflineDatasets.from_behaviour_and_expert(
            _episodes(episodes), _episodes(3).select("observation", "action", "episode"),
            metadata={"behaviour_dataset": "mc/behaviour-v0"},
        )
    OfflineDatasets.from_behaviour_and_expert(_episodes(4), _episodes(3).select("observation", "action", "episode"))


def test_second_ctrl_c_names_the_checkpoint_it_leaves(tmp_path, monkeypatch, capsys):
    """A second Ctrl-C (KeyboardInterrupt out of the run) after a checkpoint was written: the recipe says that
    checkpoint.pt holds the last checkpoint and how to resume, not that nothing was written."""
    import runpy
    import sys
    from pathlib import Path

    def interrupted(self, **kwargs):
        self.save_checkpoint()
        raise KeyboardInterrupt

    monkeypatch.setattr(WBRMTrainer, "run", interrupted)
    run_dir = tmp_path / "run"
    monkeypatch.setattr(sys, "argv", [
        "wbrm_offline.py", "ratio.steps=10", "q.steps=20", "eval.offline_value=false", "eval.episodes=50",
        "eval.train_episodes=20",
        "eval.q_samples=300", "logger=none", "env.lqr_data.behaviour_episodes=40", "env.lqr_data.expert_episodes=20",
        "env.lqr_data.parallel_envs=20", f"hydra.run.dir={run_dir}", "hydra/job_logging=none",
        "hydra/hydra_logging=none",
    ])
    with pytest.raises(SystemExit) as exit_:
        runpy.run_path(str(Path(__file__).resolve().parents[1] / "recipes" / "wbrm_offline.py"), run_name="__main__")
    err = capsys.readouterr().err
    assert exit_.value.code == 130 and (run_dir / "checkpoint.pt").is_file()
    assert f"{run_dir / 'checkpoint.pt'} holds the last checkpoint" in err and f"resume={run_dir}" in err
    assert "nothing was written" not in err


@pytest.mark.parametrize("random_episodes, noisy_episodes", [(1, 0), (1, 1)])
def test_a_minari_behaviour_dataset_of_one_or_two_episodes_is_named(tmp_path, random_episodes, noisy_episodes):
    from torchrl_wbrm.data.minari_data import MinariDataConfig, make_minari_datasets
    from torchrl_wbrm.data.minari_examples import make_mountain_car_datasets

    ids = make_mountain_car_datasets(tmp_path, expert_episodes=2, random_episodes=random_episodes,
                                     noisy_expert_episodes=noisy_episodes, seed=0)
    n = random_episodes + noisy_episodes
    with pytest.raises(ValueError, match=rf"The behaviour dataset '{ids['behaviour']}' holds {n} episode\(s\); at "
                                         r"least 4 are needed"):
        make_minari_datasets(MinariDataConfig(expert=ids["expert"], behaviour=ids["behaviour"], data_path=str(tmp_path)))


# ---------------------------------------------------------------------- Q's scale: one rule, one factor
def test_q_past_its_bound_warns_once_and_flags_the_same_rule():
    """With γ = 0.9 and max|r| = 1 no return exceeds 10: a training figure of Q past 10 · 10 warns once, naming the
    figure and the likely cause, and the results' flag reads the same limit."""
    from torchrl_wbrm.training.stops import QBound

    bound = QBound(1.0, 0.9)
    assert bound.bound == pytest.approx(10.0) and bound.limit == pytest.approx(100.0)
    assert bound.exceeded(-100.5) and not bound.exceeded(99.0) and not bound.exceeded(None)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        bound.watch({"q_mean": 99.0, "loss_value": 1e6}, step=1)  # a loss is not a Q figure
    with pytest.warns(UserWarning, match=r"\|target_value_mean\| reached 150 at step 7, past 10 · max\|r\| / "
                                         r"\(1 − γ\) = 100 .*q.init_bias"):
        bound.watch({"q_mean": 5.0, "target_value_mean": -150.0}, step=7)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        bound.watch({"q_mean": 1e9}, step=8)  # once per run


def test_a_run_reports_its_q_scale_against_its_own_bound(tmp_path):
    results = WBRMTrainer(tiny(), tmp_path, progress=False).run()
    scale = results["q_scale"]
    assert scale["factor"] == 10.0 and scale["blow_up"] == (scale["max_abs_q_mean"] > 10.0 * scale["bound"])
    assert ("q_blow_up" in results["flags"]) == scale["blow_up"]
