"""``recipes/offline_value_validation.py``: every evaluated checkpoint of a run valued from D alone, and the figures
DOPE reports (absolute error, Spearman, regret@1) with each selection criterion's regret@1."""
from __future__ import annotations

import importlib.util
import json

import pytest

from tests.inprocess import run_script
from tests.references import ROOT

SCRIPT = ROOT / "recipes" / "offline_value_validation.py"
TINY = ["ratio.steps=20", "q.steps=40", "q.eval_every=20", "eval.episodes=50", "eval.train_episodes=20",
        "env.lqr_data.behaviour_episodes=40", "env.lqr_data.expert_episodes=20", "env.lqr_data.parallel_envs=20",
        "q.num_cells=[16,16]", "q.actor_num_cells=[16,16]", "eval.q_samples=300", "ratio.num_cells=[16,16]"]


def _module():
    spec = importlib.util.spec_from_file_location("offline_value_validation", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _record(returns, values, residuals, delivered):
    rows = [{"step": 10 * (i + 1), "return": r, "offline_value": v, "held_out_bellman_residual": h}
            for i, (r, v, h) in enumerate(zip(returns, values, residuals))]
    return {"cell": "lqr_exp1", "seed": 0, "select": "last", "delivered_step": delivered,
            "delivered_return": returns[-1], "checkpoints": rows}


def test_the_figures_of_one_run_by_hand():
    m = _module()
    rec = _record(returns=[1.0, 5.0, 3.0], values=[2.0, 4.0, 9.0], residuals=[0.5, 0.1, 0.1], delivered=30)
    f = m.run_figures(rec)
    assert f["offline_value:abs_error"] == pytest.approx((1 + 1 + 6) / 3)
    assert f["offline_value:rel_error"] == pytest.approx(100 * (1 / 1 + 1 / 5 + 6 / 3) / 3)  # in percent
    assert f["offline_value:spearman"] == pytest.approx(0.5)  # ranks (1, 2, 3) against (1, 3, 2)
    assert f["offline_value:last_error"] == pytest.approx(6.0)
    assert f["regret:FQE estimate"] == pytest.approx(2.0)  # it ranks step 30 first: 5 − 3
    assert f["regret:held-out residual"] == pytest.approx(0.0)  # a tie: the earliest lowest, step 20
    assert f["regret:last step"] == pytest.approx(2.0)
    assert "regret:held-out ŵ-weighted residual" not in f  # a figure the run did not record is no criterion
    assert "offline_value_weighted:abs_error" not in f


@pytest.mark.slow
def test_the_command_values_every_checkpoint_of_a_tiny_run(tmp_path):
    out = tmp_path / "out"
    proc = run_script(SCRIPT, "run", "--cells", "lqr_exp1", "--seeds", "0", "--out", str(out), "--fqe-steps", "30",
                      "--docs-dir", "none", "--overrides", *TINY)
    assert proc.returncode == 0, proc.stderr
    (rec,) = [json.loads(line) for line in (out / "checkpoints.jsonl").read_text().splitlines()]
    history = json.loads((out / "runs" / "lqr_exp1_seed0" / "history.json").read_text())
    evaluated = {r["step"]: r for r in history if r["stage"] in ("q", "q_last")}
    assert [r["step"] for r in rec["checkpoints"]] == [20, 40]
    for row in rec["checkpoints"]:  # the online figures are the run's own evaluations of those parameters
        online = evaluated[row["step"]]
        if row["step"] == 40 and rec["delivered_step"] != 40:
            online = [r for r in history if r["stage"] == "q_last"][-1]
        assert row["return"] == online["return"]
        assert row["offline_value"] == row["offline_value"] and row["offline_value_weighted"] == row["offline_value_weighted"]
    assert "### Regret@1 of each selection criterion" in proc.stdout and "| lqr_exp1 |" in proc.stdout
    again = run_script(SCRIPT, "report", "--cells", "lqr_exp1", "--out", str(out), "--docs-dir", str(tmp_path / "docs"))
    fragment = (tmp_path / "docs" / "results" / "_generated" / "offline_value_validation.md").read_text()
    assert again.returncode == 0 and "Seeds: 1 (0): lqr_exp1." in fragment and "| lqr_exp1 |" in fragment
    again = run_script(SCRIPT, "run", "--cells", "lqr_exp1", "--seeds", "0", "--out", str(out), "--docs-dir", "none",
                       "--overrides", *TINY)
    assert again.returncode == 0 and "seed 0:" not in again.stdout  # a finished (cell, seed) is not run again
