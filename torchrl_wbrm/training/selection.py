r"""``q.select``: one criterion object per choice (:func:`make_criterion`), the best-so-far bookkeeping
(:class:`Selection`), and the selection record of ``results.json``: what ``q.select`` delivered against the best
and the last evaluated parameters, by their online returns, and how many online episodes the choice itself used.

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

import copy
import math

import torch
from tensordict import TensorDictBase

from torchrl_wbrm.keys import DENSITY_RATIO, EPISODE
from torchrl_wbrm.data.datasets import check_episodes_in_order
from torchrl_wbrm.objectives.functional import (action_cloning, bootstrapped_returns, return_residual,
                                                weighted_mean_squared_residual)

__all__ = ["EXPERT_LIKE", "ExpertLikeAction", "ExpertLikeReturn", "HeldOutResidual", "HeldOutWeightedResidual",
           "SELECTION_ONLINE_EPISODES", "Selection", "make_criterion", "selection_record"]

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


# ---------------------------------------------------------------------- the criteria
class HeldOutResidual:
    """``q.select=held_out_residual``: the mean squared Bellman residual on D's held-out episodes, every row weighing
    1 (``"held_out_bellman_residual"``, which every run with a Bellman loss reports)."""

    figure = "held_out_bellman_residual"

    def score(self, squared_residual: torch.Tensor) -> float:
        return squared_residual.mean().item()


class HeldOutWeightedResidual:
    """``q.select=held_out_weighted_residual``: the held-out rows' squared residuals weighted by their ŵ, shaped as
    D's rows are (:func:`~torchrl_wbrm.objectives.functional.weighted_mean_squared_residual`: the squared residual
    stage 2 minimises).

    Args:
        weights: the held-out rows' stored weights, in their order.
    """

    figure = "held_out_weighted_residual"

    def __init__(self, weights: torch.Tensor):
        self.weights = weights

    def score(self, squared_residual: torch.Tensor) -> float:
        return weighted_mean_squared_residual(squared_residual, self.weights.to(squared_residual.device)).item()


class ExpertLikeAction:
    """``q.select=expert_like_action``: the actor's cloning error on the rows of D's expert-like episodes,
    ``‖(μ(x_t) − a_t) / h‖² / m`` (:func:`~torchrl_wbrm.objectives.functional.action_cloning`), the actor in
    evaluation mode.

    Args:
        rows: the expert-like rows (``"observation"``, ``"action"``).
        actor: the evaluated actor.
        half_width: the action box's half-width ``h``.
        device: where the actor runs.
    """

    figure = "expert_like_action_error"

    def __init__(self, rows: TensorDictBase, actor, half_width: torch.Tensor, device):
        self.rows, self.actor, self.half_width, self.device = rows, actor, half_width, device

    def score(self, squared_residual: torch.Tensor | None = None) -> float:
        training = self.actor.training
        self.actor.eval()  # as evaluated, also where the final selection scores the last step
        try:
            mu = self.actor(self.rows.select("observation").to(self.device))["action"]
        finally:
            self.actor.train(training)
        return action_cloning(mu, self.rows["action"].to(mu), self.half_width.to(mu)).item()


class ExpertLikeReturn:
    """``q.select=expert_like_return``: Q against each row's own discounted return on the rows of D's expert-like
    episodes (:func:`~torchrl_wbrm.objectives.functional.return_residual` of
    :func:`~torchrl_wbrm.objectives.functional.bootstrapped_returns`, bootstrapped at each episode's end by the
    Bellman target).

    Args:
        rows: the expert-like episodes' rows, whole episodes in time order (``"observation"``, ``"action"``,
            ``"episode"``, ``"next"``).
        loss: the Bellman loss (its :meth:`~torchrl_wbrm.objectives.WeightedBellmanLoss.bellman_error`).
        gamma: the discount.
        device: where the loss runs.
    """

    figure = "expert_like_return_error"

    def __init__(self, rows: TensorDictBase, loss, gamma: float, device):
        check_episodes_in_order(rows, "D's expert-like episodes (q.select=expert_like_return)")
        self.rows, self.loss, self.gamma, self.device = rows, loss, gamma, device

    def score(self, squared_residual: torch.Tensor | None = None) -> float:
        d = self.rows
        q, y = self.loss.bellman_error(d.clone().set(DENSITY_RATIO, torch.ones(d.shape[0], 1)).to(self.device))
        g = bootstrapped_returns(d["next", "reward"].reshape(-1).to(y), y.reshape(-1), d[EPISODE].reshape(-1),
                                 self.gamma)
        return return_residual(q, g).item()


#: the q.select choices scored on D's expert-like episodes
EXPERT_LIKE = ("expert_like_action", "expert_like_return")


def make_criterion(select: str, *, held_out_weights=None, expert_like_rows: TensorDictBase | None = None, actor=None,
                   half_width=None, loss=None, gamma: float | None = None, device=None):
    """The criterion of ``q.select=select`` (``None`` for ``last``). ``held_out_weights()`` returns the held-out rows'
    stored weights, called only for :class:`HeldOutWeightedResidual`. An expert-like choice without expert-like rows
    (``expert_like_rows`` ``None`` or empty: ŵ ≡ 1, or no episode likelier under the expert's distribution than
    under D's) falls back to :class:`HeldOutWeightedResidual`, and its ``figure`` says so."""
    if select == "last":
        return None
    if select == "held_out_residual":
        return HeldOutResidual()
    if select in EXPERT_LIKE and expert_like_rows is not None and expert_like_rows.shape[0] > 0:
        if select == "expert_like_action":
            return ExpertLikeAction(expert_like_rows.select("observation", "action").clone(), actor, half_width,
                                    device)
        return ExpertLikeReturn(expert_like_rows.select("observation", "action", EPISODE, "next").clone(), loss,
                                gamma, device)
    if select in EXPERT_LIKE or select == "held_out_weighted_residual":
        return HeldOutWeightedResidual(held_out_weights())
    raise ValueError(f"q.select={select!r} is not known: choose one of {sorted(SELECTION_ONLINE_EPISODES)}.")


class Selection:
    """``q.select`` over stage 2's evaluations: the best evaluation's step, score and parameters so far, and, once
    the final evaluation has loaded the best parameters into the module, the last step's parameters (a resume with
    more steps goes on from them).

    Args:
        criterion: what is minimised (:func:`make_criterion`).
    """

    def __init__(self, criterion):
        self.criterion = criterion
        self.best: dict | None = None
        self.last_state: dict | None = None

    @property
    def figure(self) -> str:
        return self.criterion.figure

    def keep_if_best(self, step: int, score: float | None, module: torch.nn.Module) -> None:
        """Keep ``module``'s parameters if ``score`` is the lowest so far (the earliest wins a tie; a non-finite
        score never does)."""
        if score is None or not math.isfinite(score):
            return
        if self.best is None or score < self.best["residual"]:
            self.best = {"step": step, "residual": score, "state": _clone_state(module.state_dict())}

    def deliver(self, module: torch.nn.Module) -> None:
        """Keep the last step's parameters and load the best evaluation's into ``module``."""
        self.last_state = _clone_state(module.state_dict())
        module.load_state_dict(self.best["state"])

    def restore_last(self, module: torch.nn.Module) -> None:
        """Put the last step's parameters back into ``module`` (after :meth:`deliver`)."""
        if self.last_state is not None:
            module.load_state_dict(self.last_state)
            self.last_state = None


def _clone_state(state: dict) -> dict:
    """A detached copy of a module's ``state_dict`` (a snapshot later steps do not change)."""
    return {k: v.detach().clone() if isinstance(v, torch.Tensor) else copy.deepcopy(v) for k, v in state.items()}
