"""PNG plots like the paper's figures: the training curve, and evaluation returns against the exact optimum."""
from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from torchrl_wbrm.algos import ALGOS  # noqa: E402

__all__ = ["LOSS_TITLES", "plot_ci_rows", "plot_run"]

class _LossTitles(Mapping):
    """algo name -> the title of its training-loss panel (its losses are every ``loss*`` figure the algo's step
    reports): each registered algo's ``loss_title``, read from the registry when asked."""

    def __getitem__(self, name: str) -> str:
        if name not in ALGOS:
            raise KeyError(name)
        return ALGOS[name].loss_title

    def __iter__(self):
        return iter(ALGOS)

    def __len__(self) -> int:
        return len(ALGOS)


#: The title of the training-loss panel per algo (:class:`~torchrl_wbrm.algos.AlgoSpec`'s ``loss_title``).
LOSS_TITLES = _LossTitles()


def _finite(values: list) -> list[float]:
    return [float(v) for v in values if isinstance(v, (int, float)) and math.isfinite(v)]


def plot_run(history: list[dict], run_dir: str | os.PathLike, *, title: str = "", algo: str = "wbrm") -> list[Path]:
    """Write ``training_curve.png`` and ``evaluation.png`` from a trainer's history; returns their paths.

    The loss panel draws every ``loss*`` figure the algo reports (a log axis when all are positive), titled by
    :data:`LOSS_TITLES`. The reference line is the exact optimum (LQR, ``optimal_return_exact``), never the paper's
    87.84, which is the reward cap; for MountainCar there is no exact optimum and no line is drawn.
    """
    run_dir = Path(run_dir)
    paths = []
    train = [r for r in history if r["stage"] == "q_train"]
    evals = [r for r in history if r["stage"] == "q"]
    ratio = [r for r in history if r["stage"] == "ratio"]

    fig, axes = plt.subplots(1, 3 if ratio else 2, figsize=(13 if ratio else 9, 3.6))
    if train:
        losses = [k for k in dict.fromkeys(k for r in train for k in r) if k.startswith("loss")]
        positive = True
        for key in losses:
            rows = [r for r in train if key in r and r[key] is not None]
            axes[0].plot([r["step"] for r in rows], [r[key] for r in rows], label=key)
            values = _finite([r[key] for r in rows])
            positive = positive and bool(values) and min(values) > 0
        if losses and positive:
            axes[0].set_yscale("log")
        if len(losses) > 1:
            axes[0].legend(fontsize=8)
        axes[0].set_title(LOSS_TITLES.get(algo, f"{algo}: training losses"))
        axes[0].set_xlabel("step")
        q_key = next((k for k in ("q_mean", "actor_q_mean", "target_value_mean") if any(k in r for r in train)), None)
        if q_key is not None:
            rows = [r for r in train if q_key in r]
            axes[1].plot([r["step"] for r in rows], [r[q_key] for r in rows], label=f"{q_key} on batch")
        if evals and "q_star_mean_behaviour" in evals[-1]:
            axes[1].axhline(evals[-1]["q_star_mean_behaviour"], color="k", ls="--", label="mean Q* on behaviour data")
        axes[1].set_title("mean Q" if q_key is not None else f"mean Q ({algo} reports none per batch)")
        axes[1].set_xlabel("step")
        if q_key is not None or (evals and "q_star_mean_behaviour" in evals[-1]):
            axes[1].legend(fontsize=8)
    if ratio:
        axes[2].plot([r["step"] for r in ratio], [r["held_out_loss"] for r in ratio])
        axes[2].set_title("stage 1: held-out ratio loss")
        axes[2].set_xlabel("step")
    fig.suptitle(title)
    paths.append(save_figure(fig, run_dir / "training_curve.png"))

    if evals:
        fig, axes = plt.subplots(1, 2 if "regret" in evals[-1] else 1, figsize=(10 if "regret" in evals[-1] else 5.5, 3.6), squeeze=False)
        steps = [r["step"] for r in evals]
        ret = [r["return"] for r in evals]
        ci = [r.get("return_ci", 0.0) for r in evals]
        ax = axes[0, 0]
        ax.errorbar(steps, ret, yerr=ci, marker="o", capsize=3,
                    label=f"{algo} policy, deterministic (95% CI)")
        if "optimal_return_exact" in evals[-1]:
            ax.axhline(evals[-1]["optimal_return_exact"], color="k", ls="--", label="exact optimum")
        ax.set_xlabel("step")
        ax.set_ylabel("evaluation return")
        ax.legend(fontsize=8)
        if "regret" in evals[-1]:
            ax = axes[0, 1]
            ax.errorbar(steps, [r["regret"] for r in evals], yerr=[r["regret_ci"] for r in evals], marker="o", capsize=3)
            regrets = _finite([r["regret"] for r in evals])
            if regrets and min(regrets) > 0:
                ax.set_yscale("log")
            ax.set_xlabel("step")
            ax.set_ylabel("paired regret vs exact optimum")
        fig.suptitle(title)
        paths.append(save_figure(fig, run_dir / "evaluation.png"))
    return paths


def save_figure(fig, path: str | os.PathLike, *, dpi: int = 110, rect=None) -> Path:
    """Lay ``fig`` out (``tight_layout``, within ``rect`` when given), write it to ``path`` and close it: the end of
    every figure of the recipes and studies. Returns the path."""
    fig.tight_layout(**({} if rect is None else {"rect": rect}))
    path = Path(path)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def plot_ci_rows(ax, rows: dict[str, list[float]], *, log: bool = False) -> None:
    """One row per label on ``ax``: the mean of its values (seeds) with its 95% Student-t interval (none for a single
    value). ``log``: a log x axis, the mean floored at 1e-4 and the lower whisker stopped above zero."""
    from torchrl_wbrm.evaluation.stats import mean_ci

    for i, values in enumerate(rows.values()):
        if not values:
            continue
        ci = mean_ci(values)
        err = ci.half_width if len(values) > 1 else 0.0
        if log:
            ax.errorbar([max(ci.mean, 1e-4)], [i], xerr=[[min(err, max(ci.mean - 1e-4, 0.0))], [err]], fmt="o", capsize=3)
        else:
            ax.errorbar([ci.mean], [i], xerr=[err], fmt="o", capsize=3)
    if log:
        ax.set_xscale("log")
    ax.set_yticks(range(len(rows)), list(rows))
