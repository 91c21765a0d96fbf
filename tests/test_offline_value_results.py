"""``eval.offline_value``: the delivered actor's value by FQE on D, written to ``results.json`` beside the online
figure and printed in the summary; it reads D only and leaves the run's own figures as they were."""
from __future__ import annotations

import json

import pytest

from tests.inprocess import run_script
from tests.references import tiny_lqr_config
from torchrl_wbrm.training import WBRMTrainer
from torchrl_wbrm.training.config import EvalConfig
from torchrl_wbrm.training.offline_value import offline_value_figures
from torchrl_wbrm.training.reporting import summarise

pytestmark = pytest.mark.usefixtures("single_thread")  # tests/conftest.py: one torch thread per test

KEYS = ("offline_value", "offline_value_ci", "offline_value_low", "offline_value_high")


def test_the_run_records_and_prints_the_offline_value(tmp_path):
    on = WBRMTrainer(tiny_lqr_config(eval={"offline_value": True}), tmp_path / "on", progress=False)
    results = on.run()
    off = WBRMTrainer(tiny_lqr_config(), tmp_path / "off", progress=False).run()
    final = results["final"]
    for prefix in ("offline_value", "offline_value_weighted"):  # wbrm with a learned ŵ: both estimates
        assert final[f"{prefix}_low"] < final[prefix] < final[f"{prefix}_high"]
        assert final[f"{prefix}_ci"] == pytest.approx((final[f"{prefix}_high"] - final[f"{prefix}_low"]) / 2)
    # the same quantity as the online return (LQR: discounted, γ = 0.9, 20 steps): within a few units on tiny data
    assert abs(final["offline_value"] - final["return"]) < 5.0
    record = results["offline_value"]
    assert record["uses_environment"] is False and record["weighted"]
    assert record["steps"] == EvalConfig().offline_value_steps
    assert "γ = 0.9" in record["quantity"] and "at most 20 steps" in record["quantity"]
    assert record["episodes"] == int(on.q_train_data["episode"].unique().numel())
    # nothing else changes: the online figures are those of the run without it, and the history holds no estimate
    assert {k: v for k, v in final.items() if not k.startswith("offline_value")} == off["final"]
    assert "offline_value" not in off["final"] and "offline_value" not in off
    history = json.loads((tmp_path / "on" / "history.json").read_text())
    assert not any("offline_value" in r for r in history)
    assert json.loads((tmp_path / "on" / "results.json").read_text())["final"]["offline_value"] == final["offline_value"]
    line = [s for s in summarise(results).splitlines() if s.startswith("offline value")]
    assert line == [f"offline value (FQE on D, no environment) {final['offline_value']:.2f} ± "
                    f"{final['offline_value_ci']:.2f}   ŵ-weighted {final['offline_value_weighted']:.2f} ± "
                    f"{final['offline_value_weighted_ci']:.2f}"]
    # the command estimates it again from the run directory alone, to the same figures, and writes nothing
    before = {p: p.stat().st_mtime_ns for p in (tmp_path / "on").rglob("*")}
    proc = run_script("recipes/offline_value.py", tmp_path / "on")
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[0].endswith("env lqr_exp1  algo wbrm  seed 0  delivered step 40 of 40")
    assert f"FQE on D: {final['offline_value']:.4f} ± {final['offline_value_ci']:.4f}" in proc.stdout
    assert f"ŵ-weighted FQE on D (stage 2's weights): {final['offline_value_weighted']:.4f}" in proc.stdout
    assert "at most 20 steps" in proc.stdout and lines[-1].startswith("The environment was not run")
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "on").rglob("*")} == before


def test_the_command_refuses_a_directory_without_a_finished_run(tmp_path):
    proc = run_script("recipes/offline_value.py", tmp_path)
    assert proc.returncode != 0 and "checkpoint.pt does not exist" in proc.stderr
    WBRMTrainer(tiny_lqr_config(), tmp_path / "cut", progress=False).run(until=20)
    proc = run_script("recipes/offline_value.py", tmp_path / "cut")
    assert proc.returncode != 0 and "holds an unfinished run (stage 'q', step 20)" in proc.stderr


def test_without_a_ratio_there_is_one_estimate_and_an_unstated_quantity_none(tmp_path):
    trainer = WBRMTrainer(tiny_lqr_config(algo="brm", eval={"offline_value": True, "offline_value_steps": 50}),
                          tmp_path / "brm", progress=False)
    results = trainer.run()
    assert "offline_value" in results["final"] and "offline_value_weighted" not in results["final"]
    assert results["offline_value"]["weighted"] is False and results["offline_value"]["steps"] == 50
    figures, record = offline_value_figures(trainer.actor, trainer.q_train_data, None)
    assert figures == {} and "does not state" in record["skipped"]


def test_ratio_weighted_fqe_reads_the_unshaped_ratio(tmp_path):
    """``eval.offline_value_weights=ratio``: the weighted estimate is FQE weighted by ŵ itself over D's training
    rows, self-normalised, not by stage 2's shaped weights (ŵ^λ with the default λ < 1)."""
    from torchrl_wbrm.ratio import compute_density_ratio

    settings = {"offline_value": True, "offline_value_steps": 50}
    shaped = WBRMTrainer(tiny_lqr_config(eval=settings), tmp_path / "stage2", progress=False)
    shaped_results = shaped.run()
    trainer = WBRMTrainer(tiny_lqr_config(eval={**settings, "offline_value_weights": "ratio"}), tmp_path / "ratio",
                          progress=False)
    results = trainer.run()
    assert results["offline_value"]["weights"] == "ratio" and shaped_results["offline_value"]["weights"] == "stage2"
    assert results["final"]["offline_value"] == shaped_results["final"]["offline_value"]  # the unweighted one
    assert results["final"]["offline_value_weighted"] != shaped_results["final"]["offline_value_weighted"]
    w = compute_density_ratio(trainer.ratio_network, trainer.q_train_data).reshape(-1, 1).double()
    expected, _ = offline_value_figures(trainer.actor, trainer.q_train_data, trainer.task.return_quantity(),
                                        weights=(w / w.mean()).float(), steps=50, seed=0)
    assert results["final"]["offline_value_weighted"] == pytest.approx(expected["offline_value_weighted"], rel=1e-6)


def test_the_weighting_of_the_offline_value_is_a_choice():
    with pytest.raises(ValueError, match=r"eval.offline_value_weights='raw' is not allowed: choose one of"):
        WBRMTrainer(tiny_lqr_config(eval={"offline_value_weights": "raw"}), progress=False)


def test_the_command_builds_no_evaluator(tmp_path, monkeypatch):
    """The run-directory estimate needs the run's checkpoint and D only: no evaluation env or simulation is built
    (the task states the quantity without one), and a trainer built so refuses to run."""
    import importlib.util

    from tests.references import ROOT
    from torchrl_wbrm.tasks.lqr import LQRTask

    run_dir = tmp_path / "run"
    WBRMTrainer(tiny_lqr_config(eval={"offline_value": True, "offline_value_steps": 50}), run_dir,
                progress=False).run()
    saved = json.loads((run_dir / "results.json").read_text())["final"]

    def no_evaluator(self, eval_cfg):
        raise AssertionError("an evaluator was built")

    monkeypatch.setattr(LQRTask, "evaluator", no_evaluator)
    spec = importlib.util.spec_from_file_location("offline_value_recipe", ROOT / "recipes" / "offline_value.py")
    recipe = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(recipe)
    figures, record, run = recipe.offline_value_of_run(run_dir)
    assert figures["offline_value"] == saved["offline_value"] and record["uses_environment"] is False
    trainer = WBRMTrainer(tiny_lqr_config(), run_dir, resume=True, logger=None, progress=False, evaluation=False)
    try:
        with pytest.raises(ValueError, match="built with evaluation=False"):
            trainer.run()
    finally:
        trainer.release()
    with pytest.raises(ValueError, match="ratio.source=exact reads the evaluator's exact ratio"):
        WBRMTrainer(tiny_lqr_config(ratio={"source": "exact"}), tmp_path / "exact", progress=False, evaluation=False)
