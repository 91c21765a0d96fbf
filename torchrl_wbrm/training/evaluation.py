"""A run's evaluations: the task's evaluator (its evaluation samples and, where known, the exact ratio), stage 1's ŵ
against the truth, stage 2's evaluation of the actor and Q with ``q.select``'s bookkeeping
(:mod:`torchrl_wbrm.training.selection`), and the figures read from D alone (the offline value, Q̂'s mean over D).
"""
from __future__ import annotations

import torch

from torchrl_wbrm.keys import DENSITY_RATIO
from torchrl_wbrm.evaluation import ratio_error
from torchrl_wbrm.objectives.functional import bellman_residual
from torchrl_wbrm.training.offline_value import offline_value_figures

__all__ = ["RunEvaluation"]


class RunEvaluation:
    """The evaluations of one run of the config ``cfg``: its ``task``'s evaluator (``build=False``: none, no
    evaluation env or simulation, only the figures from D), its ``algo``'s ``policy``, ``q_value`` and
    ``bellman_loss``, D's ``train`` and ``holdout`` episodes, the networks' ``device``. ``build=False`` is refused
    where stage 2 reads the exact ratio (``ratio.source=exact``), which the evaluator holds."""

    def __init__(self, cfg, task, algo, train, holdout, device, *, build: bool = True):
        if not build and cfg.ratio.source == "exact" and algo.uses_ratio:
            raise ValueError("evaluation=False builds no evaluator, and ratio.source=exact reads the evaluator's "
                             "exact ratio: build the trainer with evaluation=True.")
        self.cfg, self.task, self.algo, self.train, self.holdout, self.device = cfg, task, algo, train, holdout, device
        self.evaluator = task.evaluator(cfg.eval) if build else None
        self.eval_samples = self.evaluator.eval_samples if build else {}  # where Q* is known
        self.true_ratio = self.evaluator.true_ratio if build else None  # the exact ratio, where known

    @torch.no_grad()
    def ratio_figures(self, network) -> dict:
        """``network``'s ŵ against the exact ratio on the evaluation's behaviour samples (where both exist)."""
        if self.true_ratio is None or network is None:
            return {}
        b = self.eval_samples["behaviour"].to(self.device)
        w_hat = network(b.clone())[DENSITY_RATIO]
        w = self.true_ratio(b.clone())[DENSITY_RATIO]
        return {f"ratio_{k}": v for k, v in ratio_error(w_hat, w).items()}

    @torch.no_grad()
    def evaluate(self, selection=None, *, final: bool = False) -> dict:
        """The current actor and Q: a flat dict of floats (the task's figures; with a Bellman loss, the
        :meth:`selection_figures`). Runs on a forked global generator: evaluating never changes what training draws."""
        ec = self.cfg.eval
        actor = self.algo.policy
        with torch.random.fork_rng():
            actor.eval()
            try:
                out = self.evaluator.evaluate(actor, episodes=ec.episodes if final else ec.train_episodes,
                                              seed=ec.seed, q_value=self.algo.q_value, device=self.device)
                if self.algo.bellman_loss is not None:
                    out.update(self.selection_figures(selection))
            finally:
                actor.train()
        return out

    @torch.no_grad()
    def selection_figures(self, selection=None) -> dict[str, float]:
        """The current Q's figures that ``q.select`` can minimise: ``"held_out_bellman_residual"``, the mean δ² (any
        residual form) on the held-out D episodes, and the figure of ``selection``'s criterion."""
        held_out = self.holdout.clone().set(DENSITY_RATIO, torch.ones(self.holdout.shape[0], 1))
        squared = bellman_residual(*self.algo.bellman_loss.bellman_error(held_out.to(self.device))).pow(2)
        out = {"held_out_bellman_residual": squared.mean().item()}
        if selection is not None:
            out[selection.figure] = selection.criterion.score(squared)
        return out

    def stage_two(self, step: int, selection, history: list, *, stop=None) -> dict:
        """Stage 2's evaluation at ``step`` with ``selection``'s bookkeeping (``None``: ``q.select=last``): during
        training it keeps the best parameters; at the last step it delivers them (the last step's own parameters are
        evaluated first, appended to ``history`` as ``"q_last"``) and records ``"selected_step"``. ``stop``: the run's
        :class:`~torchrl_wbrm.training.stops.StopSignals`, which stop a (long) evaluation at once."""
        loss, final = self.algo.loss, step == self.cfg.q.steps
        if selection is not None and final and selection.last_state is None:
            selection.keep_if_best(step, self.selection_figures(selection)[selection.figure], loss)
            if selection.best["step"] != step:  # an earlier evaluation's parameters are delivered and scored
                history.append({"stage": "q_last", "step": step, **self.evaluate(selection)})  # for "selection"
                selection.deliver(loss)
        try:
            if stop is not None:
                with stop.immediately():
                    figures = self.evaluate(selection, final=final)
            else:
                figures = self.evaluate(selection, final=final)
        except BaseException:
            if selection is not None and final:  # checkpointed as it was trained: the resumed evaluation selects again
                selection.restore_last(loss)
            raise
        if selection is not None and not final:
            selection.keep_if_best(step, figures.get(selection.figure), loss)
        if selection is not None and final:
            figures["selected_step"] = selection.best["step"]
        return figures

    def offline_value(self, weights, weighting, steps: int | None = None) -> tuple[dict, dict]:
        """:meth:`WBRMTrainer.offline_value <torchrl_wbrm.training.trainer.WBRMTrainer.offline_value>`: where stage 2
        read ``weights``, FQE weighted by them, or with ``eval.offline_value_weights=ratio`` by ``weighting``'s ŵ
        before any shaping, self-normalised."""
        ec = self.cfg.eval
        if weights is not None and ec.offline_value_weights == "ratio":
            w = weighting.raw(self.train).reshape(-1, 1).double()
            weights = (w / w.mean()).to(weights.dtype)
        with torch.random.fork_rng():
            figures, record = offline_value_figures(self.algo.policy, self.train, self.task.return_quantity(),
                                                    weights=weights, steps=steps or ec.offline_value_steps,
                                                    seed=self.cfg.seed)
        record["weights"] = None if weights is None else ec.offline_value_weights
        return figures, record

    @torch.no_grad()
    def q_mean_over_d(self, chunk: int = 8192) -> float | None:
        """The current Q̂'s mean over D's training rows (its own state-actions), by the algo's ``q_value`` (``None``
        for an algo without one, or trained on S^e alone)."""
        if self.algo.q_value is None or self.algo.data == "expert":
            return None
        q_value = self.algo.q_value
        total = sum(float(q_value(rows.to(self.device))[0].double().sum()) for rows in self.train.split(chunk))
        return total / self.train.shape[0]
