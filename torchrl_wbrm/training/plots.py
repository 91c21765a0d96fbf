"""PNG plots like the paper's figures: the training curve, and evaluation returns against the exact optimum."""
from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from torchrl_wbrm.keys import HELD_OUT_LOSS
from torchrl_wbrm.algos import ALGOS  # noqa: E402

__all__ = ["LOSS_NAMES", "LOSS_TITLES", "plot_ci_rows", "plot_run"]

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


#: readable names of the training losses the algos report (a panel each, titled by it; the key is its y-label)
LOSS_NAMES = {
    "loss_actor": "actor loss", "loss_actor_bc": "actor's cloning loss", "loss_qvalue": "Q loss",
    "loss_cql": "CQL penalty", "loss_alpha": "entropy-temperature loss", "loss_bc": "behaviour-cloning loss",
    "loss_value": "value loss",
}
#: the datasets' mean episode returns (``results["data"]``) drawn beside the evaluation return
DATA_RETURNS = {"expert_mean_return": ("expert data", "tab:green"), "behaviour_mean_return": ("behaviour data",
                                                                                              "tab:red")}


def _loss_panel(ax, train: list[dict], key: str, title: str) -> None:
    """One training loss on its own axes: its own scale (log when it stays positive), its name as the y-label."""
    rows = [r for r in train if isinstance(r.get(key), (int, float))]
    ax.plot([r["step"] for r in rows], [r[key] for r in rows], color="tab:blue")
    values = _finite([r[key] for r in rows])
    if values and min(values) > 0 and max(values) / min(values) > 10:
        ax.set_yscale("log")
    ax.set_title(title, fontsize=10)
    ax.set_ylabel(key)
    ax.set_xlabel("step")


def plot_run(history: list[dict], run_dir: str | os.PathLike, *, title: str = "", algo: str = "wbrm",
             data: dict | None = None) -> list[Path]:
    """Write ``training_curve.png`` and ``evaluation.png`` from a trainer's history; returns their paths.

    ``training_curve.png`` has one panel per ``loss*`` figure the algo reports, each on its own scale (a log axis
    when it stays positive over more than a decade) with the figure's name as its y-label, titled by
    :data:`LOSS_NAMES` (the Bellman family's and BC's main loss by :data:`LOSS_TITLES`); then the mean Q on the batch
    (when the algo reports one) beside the mean Q* on behaviour data (LQR); then stage 1's held-out ratio loss. ``evaluation.png``: the evaluation return with its 95% CI; the reference lines are the exact
    optimum (LQR, ``optimal_return_exact``), never the paper's 87.84, which is the reward cap, and the datasets'
    own mean episode returns (``data``: the results' ``"data"``, keys ``expert_mean_return`` and
    ``behaviour_mean_return``) when given; beside it, on LQR, the paired regret.
    """
    run_dir = Path(run_dir)
    paths = []
    train = [r for r in history if r["stage"] == "q_train"]
    evals = [r for r in history if r["stage"] == "q"]
    ratio = [r for r in history if r["stage"] == "ratio"]

    losses = [k for k in dict.fromkeys(k for r in train for k in r) if k.startswith("loss")]
    q_key = next((k for k in ("q_mean", "actor_q_mean", "target_value_mean") if any(k in r for r in train)), None)
    panels = len(losses) + (1 if q_key else 0) + (1 if ratio else 0)
    cols = max(panels, 1) if panels <= 3 else 2 if panels == 4 else 3  # 4 panels as 2 x 2
    rows_ = max(1, math.ceil(panels / cols))
    fig, axes = plt.subplots(rows_, cols, figsize=(4.4 * cols, 3.3 * rows_), squeeze=False)
    flat = list(axes.flat)
    i = 0
    for n, key in enumerate(losses):  # the algo's own title on its main loss (the Bellman family's, BC's)
        main = n == 0 and key in ("loss_value", "loss_bc") and algo in LOSS_TITLES
        _loss_panel(flat[i], train, key, LOSS_TITLES[algo] if main else LOSS_NAMES.get(key, key))
        i += 1
    if q_key is not None:
        ax = flat[i]
        i += 1
        rows = [r for r in train if q_key in r]
        ax.plot([r["step"] for r in rows], [r[q_key] for r in rows], label=f"{q_key} on the batch")
        if evals and "q_star_mean_behaviour" in evals[-1]:
            ax.axhline(evals[-1]["q_star_mean_behaviour"], color="k", ls="--", label="mean Q* on behaviour data")
        ax.set_title("mean Q", fontsize=10)
        ax.set_ylabel("mean Q")
        ax.set_xlabel("step")
        ax.legend(fontsize=8)
    if ratio:
        ax = flat[i]
        i += 1
        ax.plot([r["step"] for r in ratio], [r[HELD_OUT_LOSS] for r in ratio], color="tab:purple")
        ax.set_title("stage 1: density ratio ŵ", fontsize=10)
        ax.set_ylabel("held-out ratio loss")
        ax.set_xlabel("step")
    for ax in flat[i:]:
        ax.set_visible(False)
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
        for key, (label, colour) in DATA_RETURNS.items():
            value = (data or {}).get(key)
            if isinstance(value, (int, float)) and math.isfinite(value):
                ax.axhline(value, color=colour, ls=":", label=f"{label}: mean episode return {value:.4g}")
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
    from torchrl_wbrm.training.results import atomic_write

    fig.tight_layout(**({} if rect is None else {"rect": rect}))
    path = Path(path)
    # written whole, never through a link planted under its name (format from the suffix, as savefig(path) does)
    atomic_write(path, lambda f: fig.savefig(f, dpi=dpi, format=path.suffix.lstrip(".") or None))
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
