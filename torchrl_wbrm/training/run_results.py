"""What a run's ``results.json`` holds, built from what the run recorded: :func:`finished_results` (the final
figures, the weights, stage 1's outcome, the data, the selection, Q's scale and the flags) and
:func:`diverged_results` (where a divergence stopped it). The trainer writes them
(:meth:`~torchrl_wbrm.training.trainer.WBRMTrainer.results`).
"""
from __future__ import annotations

import math
from pathlib import Path

from torchrl_wbrm.keys import HISTORY, RESULTS
from torchrl_wbrm.training.logging import log_run_summary
from torchrl_wbrm.training.reporting import below_behaviour, return_fell
from torchrl_wbrm.training.results import json_safe, write_json
from torchrl_wbrm.training.selection import selection_record

__all__ = ["diverged_results", "finished_results", "q_scale", "write_results"]


def q_scale(final: dict, last_train: dict | None, bound, q_mean_data: float | None = None) -> dict:
    """The largest |mean Q̂| the run reports (``final``'s ``q_mean*`` figures, the last training figures of Q, and
    ``q_mean_data``, the delivered Q̂'s mean over D's training rows), against ``bound`` (the run's
    :class:`~torchrl_wbrm.training.stops.QBound`): ``blow_up`` where it is past the bound's limit."""
    values = {k: v for k, v in final.items() if k.startswith("q_mean")}
    if q_mean_data is not None:
        values["q_mean_data"] = q_mean_data
    if last_train:
        values.update({f"train_{k}": v for k, v in last_train.items() if k in bound.FIGURES})
    values = {k: abs(float(v)) for k, v in values.items() if isinstance(v, (int, float)) and math.isfinite(v)}
    largest = max(values.values(), default=None)
    return {"max_abs_q_mean": largest, "figure": max(values, key=values.get) if values else None,
            "bound": bound.bound, "factor": bound.factor, "blow_up": bound.exceeded(largest)}


def diverged_results(cfg, history: list[dict], err, *, checkpoint_stage: str | None, data_seconds: float,
                     config: dict) -> dict:
    """``results.json`` of a run stopped by divergence (``err``, a
    :class:`~torchrl_wbrm.training.stops.TrainingDiverged`): ``"status": "diverged"`` and where."""
    final = [r for r in history if r["stage"] == "q"]
    return json_safe({
        "status": "diverged",
        "env": cfg.env.name,
        "algo": cfg.algo,
        "seed": cfg.seed,
        "diverged": {"stage": err.stage, "step": err.step, "figure": err.figure, "value": repr(err.value),
                     "message": str(err), "checkpoint_step": err.checkpoint_step,
                     "checkpoint_stage": checkpoint_stage},
        "final": final[-1] if final else {},
        "flags": ["diverged"],
        "data_seconds": data_seconds,
        "config": config,
    })


def finished_results(cfg, history: list[dict], *, datasets, weights: dict, ratio_source: str,
                     ratio_best: dict | None, ratio_check: dict | None, selection_figure: str | None,
                     offline_value: tuple[dict, dict] | None, bound, q_mean_data: float | None,
                     data_seconds: float, config: dict) -> dict:
    """``results.json`` of a finished run, from its ``history`` and what it holds: ``datasets`` (sizes and returns),
    the ``weights`` figures, stage 1's fitter's best state (``ratio_best``, ``None`` without stage 1) and verdict,
    the figure ``q.select`` minimised, the offline value (``(figures, record)`` or ``None``), the Q ``bound`` and
    the delivered Q̂'s mean over D. The flags: ``q_blow_up``, the fitter's (``ratio_collapse``,
    ``ratio_worse_than_uniform``), ``below_behaviour``, ``return_fell``."""
    final = [r for r in history if r["stage"] == "q"]
    ratio_records = [r for r in history if r["stage"] == "ratio"]
    results = {
        "status": "finished",
        "env": cfg.env.name,
        "algo": cfg.algo,
        "seed": cfg.seed,
        "final": final[-1] if final else {},
        "weights": weights,
        "ratio": {
            "source": ratio_source,
            "best_held_out_loss": ratio_best["loss"] if ratio_best is not None else None,
            "best_step": ratio_best.get("step") if ratio_best is not None else None,
            "steps_run": ratio_records[-1]["step"] if ratio_records else 0,
            **({k: v for k, v in ratio_records[-1].items() if k.startswith("ratio_")} if ratio_records else {}),
        },
        "data": {**datasets.sizes(), **{k: v for k, v in datasets.metadata.items() if k.endswith("return")}},
        "data_seconds": data_seconds,
        "config": config,
    }
    drawn = datasets.metadata.get("expert_episode_ids")
    if drawn is not None:  # env.minari.expert_episodes: which of the expert dataset's episodes this seed drew
        results["data"]["expert_episode_ids"] = drawn
    if ratio_best is not None and ratio_records:
        best = [r for r in ratio_records if r["step"] == ratio_best.get("step")]
        if best:
            results["ratio"].update({k: v for k, v in best[0].items() if k.startswith("ratio_")})
    results["selection"] = selection_record(  # delivered, best and last by their online returns
        history, cfg.q.select, selection_figure, episodes=cfg.eval.episodes, train_episodes=cfg.eval.train_episodes,
        steps=cfg.q.steps)
    if offline_value is not None:  # the delivered actor's value by FQE on D: no environment
        figures, results["offline_value"] = offline_value
        results["final"] = {**results["final"], **figures}
    train = [r for r in history if r["stage"] == "q_train"]
    results["q_scale"] = q_scale(results["final"], train[-1] if train else None, bound, q_mean_data)
    results["flags"] = ["q_blow_up"] if results["q_scale"]["blow_up"] else []
    if ratio_check is not None:  # the fitter's verdict: ratio_collapse, ratio_worse_than_uniform
        results["ratio"]["check"] = ratio_check
        results["flags"].extend(ratio_check.get("flags", ["ratio_collapse"] if ratio_check.get("collapse") else []))
    results["behaviour_check"] = below_behaviour(results["final"], results["data"])
    if results["behaviour_check"]["below"]:
        results["flags"].append("below_behaviour")
    results["return_check"] = return_fell(history, results["data"])
    if results["return_check"]["fell"]:
        results["flags"].append("return_fell")
    return json_safe(results)


def write_results(run_dir: Path, results: dict, history: list[dict], *, plots: str | None = None,
                  logger=None) -> dict:
    """Write ``results`` (``results.json``) and ``history`` (``history.json``) into ``run_dir``, then, where ``plots``
    (their title), the plots (:func:`~torchrl_wbrm.training.plots.plot_run`) and ``logger``'s summary (wandb: final
    figures with CIs, plots, a results table): the figures are on disk before any plot is drawn, so a failing plot
    cannot lose them. Returns ``results``."""
    write_json(run_dir / RESULTS, results)
    write_json(run_dir / HISTORY, history)
    if plots is not None:
        from torchrl_wbrm.training.plots import plot_run

        plot_run(history, run_dir, title=plots, algo=results["algo"], data=results.get("data"))
    if logger is not None:
        log_run_summary(logger, results, run_dir)
    return results
