"""wandb dashboards, read back from real offline runs with wandb's own reader (``wandb leet inspect``), no mocks.

The recipe's run on test_minari.py's Minari datasets (memoised in minari_helpers) serves both tests below that read it,
in this one file, so that one worker of ``pytest -n 2 --dist loadfile`` runs it once: that it learns, and its
dashboard.
"""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from minari_helpers import GROUP, leet, minari_wandb_run


def _records(run: Path) -> list[dict]:
    return [json.loads(line) for line in leet("inspect", "--json", str(run)).splitlines() if line.strip()]


def _run_record(records: list[dict]) -> dict:
    return next(r["run"] for r in records if r.get("type") == "run")


@pytest.mark.slow
def test_recipe_learns_on_minari_datasets():
    """The recipe on the Minari datasets beats the behaviour data's mean return by a margin (seed 0)."""
    run_dir, stdout, stderr, results = minari_wandb_run()
    final, data = results["final"], results["data"]
    assert results["status"] == "finished" and results["env"] == "minari"
    behaviour, expert = data["behaviour_mean_return"], data["expert_mean_return"]
    assert behaviour < expert
    # measured (seed 0): see the README's "Your own data: Minari"
    assert final["return"] - final["return_ci"] > behaviour + 10.0, (final, data)
    assert final["data_behaviour_mean_return"] == pytest.approx(behaviour)
    assert "datasets' mean episode returns: behaviour" in stdout and "over the evaluation episodes" in stdout
    # D and S^b come from the behaviour dataset, split by episode; S^e is the expert dataset
    assert data["transitions"] + data["behaviour_samples"] > data["expert_samples"] > 0
    # console: torchrl's storage INFO lines are silenced by default
    assert "[INFO]" not in stdout + stderr


@pytest.mark.slow
def test_recipe_run_dashboard():
    run_dir, stdout, stderr, results = minari_wandb_run()
    run = run_dir / "wandb" / "latest-run"
    summary = json.loads(leet("inspect", "--summary", "--json", str(run)))
    assert summary["state"] == "finished" and summary["exit_code"] == 0
    values = summary["summary"]
    # the final figures with their CIs, the datasets' figures, the status
    for key in ("final/return", "final/return_ci", "final/return_stderr", "final/held_out_bellman_residual",
                "data/behaviour_mean_return", "data/expert_mean_return", "data/transitions", "weights/ess"):
        assert key in values, key
    assert values["final/return"] == pytest.approx(results["final"]["return"])
    assert values["final/return_ci"] == pytest.approx(results["final"]["return_ci"])
    assert values["status"] == "finished"
    # step metrics in sections
    assert {"ratio/loss_density_ratio", "q/loss_value", "eval/return", "eval/step", "q/step"} <= values.keys()
    assert values["eval/step"] == results["config"]["q"]["steps"]  # evaluation plotted against the training step
    # media: the plots as images, the final results as a table
    assert values["plots/training_curve"]["_type"] == "image-file"
    assert values["plots/evaluation"]["_type"] == "image-file"
    assert values["results"]["_type"] == "table-file" and values["results"]["ncols"] == 4
    assert (run / values["results"]["path"]).is_file() or any(run.rglob("results_*.table.json"))
    table = json.loads(next(run.rglob("results_*.table.json")).read_text())
    assert table["columns"] == ["figure", "value", "ci95", "stderr"]
    assert ["return", pytest.approx(results["final"]["return"]), pytest.approx(results["final"]["return_ci"]),
            pytest.approx(results["final"]["return_stderr"])] in table["data"]
    # the resolved config, a readable name, group / job_type / tags
    assert summary["config"]["env"]["minari"]["expert"] == results["config"]["env"]["minari"]["expert"]
    assert summary["name"] == "wbrm · minari · seed 0"
    assert summary["tags"] == ["minari", "wbrm", "seed0"]
    records = _records(run)
    record = _run_record(records)
    assert record["run_group"] == GROUP and record["job_type"] == "wbrm"
    step_metrics = {r["metric"]["name"]: r["metric"].get("step_metric") for r in records if r.get("type") == "metric"}
    assert step_metrics["eval/return"] == "eval/step" and step_metrics["q/loss_value"] == "q/step"
    assert step_metrics["ratio/loss_density_ratio"] == "ratio/step"


def test_study_summary_run(tmp_path):
    """A study's tables (Markdown) and figures go to a summary run of its group."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchrl_wbrm.training.logging import log_study_summary, markdown_tables

    tables = tmp_path / "tables.md"
    tables.write_text("## Table 2 (LQR)\n\n| algorithm | return |\n|---|---|\n| wbrm | 85.39 ± 0.04 |\n| bc | 85.44 ± 0.00 |\n\n"
                      "## Regret\n\n| algorithm | regret |\n|---|---|\n| wbrm | 0.05 ± 0.01 |\n\n"
                      "### Headline: every method on every environment (LQR: paired regret, lower is better; "
                      "otherwise: return, higher is better)\n\n| algorithm | lqr_exp1 regret |\n|---|---|\n| wbrm | 0.006 |\n")
    headline = "headline_every_method_on_every_environment_lqr_paired_regret"  # cut at 60 characters for wandb
    assert list(markdown_tables(tables.read_text())) == ["table_2_lqr", "regret", headline]
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    fig.savefig(tmp_path / "study.png")
    plt.close(fig)
    run_folder = log_study_summary("test_study", tmp_path, tables=[tables], figures=[tmp_path / "study.png"])
    assert run_folder is not None
    summary = json.loads(leet("inspect", "--summary", "--json", run_folder))
    values = summary["summary"]
    assert values["tables/tables/table_2_lqr"]["_type"] == "table-file"
    assert values["tables/tables/table_2_lqr"]["nrows"] == 2
    assert values["tables/tables/regret"]["_type"] == "table-file"
    assert values[f"tables/tables/{headline}"]["nrows"] == 1  # a long heading's table is logged too
    assert values["figures/study"]["_type"] == "image-file"
    record = _run_record(_records(Path(run_folder)))
    assert record["run_group"] == "test_study" and record["job_type"] == "summary"
