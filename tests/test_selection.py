"""``q.select=held_out_residual``: the run delivers, and scores at the end, the parameters of the evaluation whose
Bellman residual on the held-out D episodes was lowest.

The residual is replaced by a known sequence (``FAKE``, by the step the trainer is at), so that which step must be
chosen is known beforehand; under a constant learning rate the chosen parameters are then exactly those of a run that
stops at that step, and their final figures must be equal, bit for bit."""
from __future__ import annotations

import pytest

from tests.references import tiny_lqr_config
from torchrl_wbrm.training import WBRMTrainer
from torchrl_wbrm.training.evaluation import RunEvaluation
from torchrl_wbrm.training.seeds import run_seeds

pytestmark = pytest.mark.usefixtures("single_thread")  # tests/conftest.py: one torch thread per test

#: the held-out residual the patched trainer reports at each evaluation step (lowest at 20 of 40; 60 beats it)
FAKE = {10: 3.0, 20: 1.0, 30: 2.0, 40: 2.5, 50: 2.0, 60: 0.5}


def tiny(**overrides):
    return tiny_lqr_config({"q": {"lr_schedule": "constant", "eval_every": 10, "select": "held_out_residual"},
                            "eval": {"q_samples": 400}, "checkpoint_every": 10}, **overrides)


@pytest.fixture
def fake_residual(monkeypatch):
    stage_two = RunEvaluation.stage_two

    def at_step(self, step, *args, **kwargs):  # the step of the evaluation, for fake
        self.fake_step = step
        return stage_two(self, step, *args, **kwargs)

    def fake(self, selection=None):
        return dict.fromkeys(("held_out_bellman_residual", "held_out_weighted_residual"), FAKE[self.fake_step])

    monkeypatch.setattr(RunEvaluation, "stage_two", at_step)
    monkeypatch.setattr(RunEvaluation, "selection_figures", fake)


FIGURES = ("regret", "return", "q_error_expert", "q_error_behaviour")


def _same_final(a: dict, b: dict) -> None:
    for key in FIGURES:
        assert a["final"][key] == b["final"][key], key


def test_the_lowest_held_out_residual_is_delivered_and_scored(fake_residual, tmp_path):
    chosen = WBRMTrainer(tiny(), tmp_path / "select", progress=False).run()
    assert chosen["final"]["selected_step"] == 20 and chosen["final"]["step"] == 40
    stopped = WBRMTrainer(tiny(q={"steps": 20, "select": "last"}), tmp_path / "stop20", progress=False).run()
    assert "selected_step" not in stopped["final"]
    _same_final(chosen, stopped)
    last = WBRMTrainer(tiny(q={"select": "last"}), tmp_path / "last", progress=False).run()
    assert chosen["final"]["regret"] != last["final"]["regret"]  # the selection changed what is scored


def test_the_seeds_in_one_process_select_each_seeds_best(fake_residual, tmp_path):
    chosen = run_seeds(tiny(seeds=[0, 1]), tmp_path / "select", progress=False)
    stopped = run_seeds(tiny(seeds=[0, 1], q={"steps": 20, "select": "last"}), tmp_path / "stop20", progress=False)
    for a, b in zip(chosen["runs"], stopped["runs"]):
        assert a["final"]["selected_step"] == 20
        _same_final(a, b)


def test_an_interrupted_run_selects_as_the_uninterrupted_one(fake_residual, tmp_path):
    whole = WBRMTrainer(tiny(), tmp_path / "whole", progress=False).run()
    WBRMTrainer(tiny(), tmp_path / "cut", progress=False).run(until=30)
    resumed = WBRMTrainer(tiny(), tmp_path / "cut", progress=False, resume=True).run()
    assert resumed["final"]["selected_step"] == 20
    _same_final(resumed, whole)


def test_a_larger_budget_continues_from_the_last_step_not_the_selected_one(fake_residual, tmp_path):
    WBRMTrainer(tiny(), tmp_path / "run", progress=False).run()  # 40 steps, step 20's parameters loaded
    extended = WBRMTrainer(tiny(q={"steps": 60}), tmp_path / "run", progress=False, resume=True).run()
    straight = WBRMTrainer(tiny(q={"steps": 60}), tmp_path / "straight", progress=False).run()
    assert extended["final"]["selected_step"] == straight["final"]["selected_step"] == 60
    # step 40's own parameters are counted by their own evaluation, not by the step-20 parameters scored at 40
    assert extended["selection"]["evaluations"] == straight["selection"]["evaluations"] == 6
    assert extended["selection"]["best"] == straight["selection"]["best"]
    _same_final(extended, straight)


def test_a_finished_run_evaluated_anew_keeps_its_selection(fake_residual, tmp_path):
    evaluation = {"episodes": 80, "train_episodes": 20, "q_samples": 400}
    first = WBRMTrainer(tiny(), tmp_path / "run", progress=False).run()
    again = WBRMTrainer(tiny(eval=evaluation), tmp_path / "run", progress=False, resume=True).run()
    assert again["final"]["selected_step"] == first["final"]["selected_step"] == 20
    assert again["final"]["return"] != first["final"]["return"]  # evaluated anew, on 80 episodes
    stopped = WBRMTrainer(tiny(q={"steps": 20, "select": "last"}, eval=evaluation), tmp_path / "stop20",
                          progress=False).run()
    _same_final(again, stopped)  # step 20's parameters, not the last step's


@pytest.mark.parametrize("algo", ["wbrm", "brm"])
def test_the_weighted_criterion_weighs_each_held_out_row_by_its_w(algo, tmp_path):
    """``held_out_weighted_residual`` is recorded at every evaluation and chosen by; with ŵ ≡ 1 (brm) it is the
    unweighted residual, with the fitted ŵ (wbrm) it is not."""
    run = WBRMTrainer(tiny(algo=algo, q={"select": "held_out_weighted_residual"}), tmp_path / algo, progress=False)
    results = run.run()
    records = [r for r in run.history if r["stage"] == "q"]
    weighted = {r["step"]: r["held_out_weighted_residual"] for r in records[:-1]}
    unweighted = {r["step"]: r["held_out_bellman_residual"] for r in records[:-1]}
    assert (weighted == unweighted) == (algo == "brm")
    best, final = min(weighted, key=weighted.get), records[-1]["held_out_weighted_residual"]
    if results["final"]["selected_step"] == 40:  # the last step's parameters are the best: none earlier was lower
        assert final <= weighted[best]
    else:  # an earlier evaluation's: the lowest one, scored again on the same held-out rows
        assert results["final"]["selected_step"] == best and final == weighted[best]


def test_an_algo_without_a_bellman_residual_is_refused(tmp_path):
    with pytest.raises(ValueError, match="q.select=held_out_residual .* algo=td3bc"):
        WBRMTrainer(tiny(algo="td3bc"), tmp_path / "td3bc", progress=False)


def test_an_unknown_choice_is_refused(tmp_path):
    with pytest.raises(ValueError, match=r"q.select='best' is not allowed"):
        WBRMTrainer(tiny(q={"select": "best"}), tmp_path / "best", progress=False)


def test_the_selection_record_names_delivered_best_and_last_by_their_online_returns(fake_residual, tmp_path):
    """``results.json``'s ``selection``: the delivered parameters (step 20) by the final evaluation, the last step's
    (40) by an evaluation of their own on ``eval.train_episodes`` episodes, equal to a ``q.select=last`` run's final
    evaluation on as many episodes; the best is the highest return among the evaluations; zero online episodes."""
    trainer = WBRMTrainer(tiny(), tmp_path / "select", progress=False)
    results = trainer.run()
    sel = results["selection"]
    assert sel["select"] == "held_out_residual" and sel["online_episodes_used_by_selection"] == 0
    assert sel["delivered"] == {"step": 20, "episodes": 50, "return": results["final"]["return"],
                                "return_ci": results["final"]["return_ci"]}
    assert sel["last"]["step"] == 40 and sel["last"]["episodes"] == 20
    last = WBRMTrainer(tiny(q={"select": "last"}, eval={"episodes": 20}), tmp_path / "last", progress=False).run()
    assert sel["last"]["return"] == last["final"]["return"]
    during = {r["step"]: r["return"] for r in trainer.history if r["stage"] == "q" and r["step"] < 40}
    candidates = {**during, 40: sel["last"]["return"]}
    assert sel["best"]["return"] == max(candidates.values()) and sel["evaluations"] == 4
    assert sel["best"]["step"] == max(candidates, key=candidates.get)
    assert sel["regret"] == pytest.approx(sel["best"]["return"] - during[20]) and sel["regret"] >= 0
    plain = last["selection"]  # q.select=last delivers the last step's parameters, scored by the final evaluation
    assert plain["select"] == "last" and plain["figure"] is None and plain["online_episodes_used_by_selection"] == 0
    assert plain["delivered"] == plain["last"] and plain["delivered"]["step"] == 40
