r"""The selection record of ``results.json``: what ``q.select`` delivered against the best and the last evaluated
parameters, by their online returns, and how many online episodes the choice itself used.

Every criterion of ``q.select`` reads D alone (the held-out Bellman residual, ŵ-weighted or not, or D's expert-like
episodes; ``last`` reads nothing), so the selection uses zero online episodes; the online returns recorded here are
the evaluations the trainer runs anyway, read from its history, and serve only to report what the choice cost:

- ``delivered``: the final evaluation (``eval.episodes`` episodes) of the parameters ``q.select`` delivered;
- ``last``: the last step's parameters: the final evaluation itself where they are the delivered ones, else the
  evaluation of the last step's parameters the trainer runs before loading the selected ones (``eval.train_episodes``
  episodes, history stage ``"q_last"``);
- ``best``: the highest online return among the evaluations during training (``eval.train_episodes`` episodes each)
  and the last step's; the delivered step was one of them.

Each entry names its step, its return (and its normalised score where the task has one) and the episodes that
figure averages; ``regret`` is ``best.return`` minus the return of the delivered parameters' own entry among the
candidates (their evaluation during training; the final evaluation where they are the last step's).
"""
from __future__ import annotations

__all__ = ["SELECTION_ONLINE_EPISODES", "selection_record"]

#: online episodes each ``q.select`` criterion reads to choose (all of them read D only)
SELECTION_ONLINE_EPISODES = {"last": 0, "held_out_residual": 0, "held_out_weighted_residual": 0,
                             "expert_like_action": 0, "expert_like_return": 0}

_FIGURES = ("return", "return_ci", "normalised_score", "normalised_score_ci")


def _entry(record: dict, episodes) -> dict:
    out = {"step": record["step"], "episodes": episodes}
    out.update({k: record[k] for k in _FIGURES if k in record})
    return out


def selection_record(history: list[dict], select: str, figure: str | None, *, episodes, train_episodes,
                     steps: int) -> dict | None:
    """The ``"selection"`` entry of ``results.json`` from the trainer's ``history`` (see the module docstring).
    ``select``: the ``q.select`` setting; ``figure``: the evaluation figure it minimised (``None`` for ``last``; a
    fallback is named here); ``episodes``/``train_episodes``: the final and the periodic evaluations' sizes;
    ``steps``: the stage-2 budget. ``None`` before the final evaluation exists."""
    evaluations = [r for r in history if r["stage"] == "q"]
    if not evaluations or evaluations[-1]["step"] != steps:
        return None
    final = evaluations[-1]
    delivered_step = final.get("selected_step", steps)
    during = {}  # step -> the latest online evaluation of that step's own parameters, before the last step
    for r in history:  # (a run resumed with a larger budget holds its earlier final evaluation and "q_last")
        if r["step"] < steps and (r["stage"] == "q_last" or (r["stage"] == "q" and r.get("selected_step", r["step"])
                                                             == r["step"])):
            during[r["step"]] = (r, episodes if "selected_step" in r else train_episodes)
    last_records = [r for r in history if r["stage"] == "q_last" and r["step"] == steps]
    if delivered_step == steps:
        last_pair = ({**final, "step": steps}, episodes)
    else:  # None: a run whose final evaluation predates the last step's own (not recorded)
        last_pair = (last_records[-1], train_episodes) if last_records else None
    candidates = [during[k] for k in sorted(during)] + ([last_pair] if last_pair else [])
    candidates = [(r, n) for r, n in candidates if r.get("return") is not None]
    best = max(candidates, key=lambda c: c[0]["return"]) if candidates else None  # the earliest wins a tie
    delivered = _entry(final, episodes)
    delivered["step"] = delivered_step
    same = [r for r, _ in candidates if r["step"] == delivered_step]
    record = {
        "select": select,
        "figure": figure,
        "online_episodes_used_by_selection": SELECTION_ONLINE_EPISODES.get(select),
        "evaluations": len(candidates),
        "delivered": delivered,
        "best": _entry(*best) if best else None,
        "last": _entry(*last_pair) if last_pair else None,
        "selected_step": delivered_step,
    }
    if same and best:  # against the delivered parameters' own entry among the candidates
        record["regret"] = best[0]["return"] - same[-1]["return"]
    return record
