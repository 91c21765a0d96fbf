"""torchrl_wbrm.training.plots: the run's figures, read back from matplotlib: each loss on its own panel and scale, every panel's y-axis
labelled, and the datasets' returns drawn beside the evaluation return."""
from __future__ import annotations

import math

import pytest

from torchrl_wbrm.training import plots


@pytest.fixture
def figures(monkeypatch):
    """Every figure :func:`plots.plot_run` saves, as ``{file name: figure}`` (saved as usual, kept open)."""
    kept = {}

    def keep(fig, path, **kwargs):
        kept[str(path).rsplit("/", 1)[-1]] = fig
        fig.tight_layout()
        fig.savefig(path)
        return path

    monkeypatch.setattr(plots, "save_figure", keep)
    yield kept
    for fig in kept.values():
        plots.plt.close(fig)


def _history(algo_losses: dict[str, float], *, ratio: bool = True, q_star: float | None = 99.2) -> list[dict]:
    history = []
    for step in range(50, 1001, 50):
        wiggle = 1 + 0.2 * math.sin(step / 100)
        history.append({"stage": "q_train", "step": step, "q_mean": 96 + step / 400,
                        **{k: v * wiggle for k, v in algo_losses.items()}})
    for step in (500, 1000):
        history.append({"stage": "q", "step": step, "return": 85.4, "return_ci": 0.1,
                        **({"q_star_mean_behaviour": q_star} if q_star is not None else {})})
    if ratio:
        history += [{"stage": "ratio", "step": s, "held_out_loss": -10 - s / 100} for s in (100, 200, 300)]
    return history


def _visible(fig):
    return [ax for ax in fig.axes if ax.get_visible()]


def test_each_loss_has_its_own_panel_scale_and_label(tmp_path, figures):
    """The weighted residual (about 0.02) and the actor loss (about −99) on separate axes: the residual's axis spans
    its own values, not the actor's."""
    plots.plot_run(_history({"loss_value": 0.02, "loss_actor": -99.0}), tmp_path, title="wbrm", algo="wbrm")
    fig = figures["training_curve.png"]
    axes = {ax.get_ylabel(): ax for ax in _visible(fig)}
    assert set(axes) == {"loss_value", "loss_actor", "mean Q", "held-out ratio loss"}, list(axes)
    low, high = axes["loss_value"].get_ylim()
    assert 0.0 < low < 0.016 and 0.024 < high < 0.1, (low, high)  # the residual fills its panel
    low, high = axes["loss_actor"].get_ylim()
    assert -130 < low < high < -70
    assert axes["loss_value"].get_title() == plots.LOSS_TITLES["wbrm"] and axes["loss_actor"].get_title()
    assert all(ax.get_xlabel() == "step" for ax in _visible(fig))
    assert (tmp_path / "training_curve.png").is_file()


def test_many_losses_and_no_batch_q(tmp_path, figures):
    plots.plot_run(_history({"loss_actor": -95.0, "loss_actor_bc": 0.3, "loss_qvalue": 1.5, "loss_cql": -9.0,
                             "loss_alpha": 0.02}, ratio=False), tmp_path, algo="cql")
    labels = [ax.get_ylabel() for ax in _visible(figures["training_curve.png"])]
    assert labels == ["loss_actor", "loss_actor_bc", "loss_qvalue", "loss_cql", "loss_alpha", "mean Q"]
    assert all(ax.get_title() for ax in _visible(figures["training_curve.png"]))


def test_the_evaluation_figure_draws_the_datasets_returns(tmp_path, figures):
    data = {"expert_mean_return": 93.54, "behaviour_mean_return": 71.96, "transitions": 100}
    plots.plot_run(_history({"loss_value": 0.3}, q_star=None), tmp_path, algo="wbrm", data=data)
    (ax,) = _visible(figures["evaluation.png"])
    lines = {line.get_label(): line.get_ydata()[0] for line in ax.get_lines()}
    assert lines["expert data: mean episode return 93.54"] == pytest.approx(93.54)
    assert lines["behaviour data: mean episode return 71.96"] == pytest.approx(71.96)
    low, high = ax.get_ylim()
    assert low < 71.96 and high > 93.54 and ax.get_ylabel() == "evaluation return"
