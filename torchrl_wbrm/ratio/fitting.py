"""Stage 1 without a trainer: fit ŵ ≈ dP^e/dP^b on behaviour and expert state-actions, with a held-out split and
early stopping.

:class:`DensityRatioFitter` holds the pieces (loss, optimiser, training buffers, held-out sets, best state) and
exposes one gradient step (:meth:`~DensityRatioFitter.step`), one held-out evaluation with best-state tracking and
patience (:meth:`~DensityRatioFitter.evaluate`), ``state_dict``/``load_state_dict`` for checkpoints and a
:meth:`~DensityRatioFitter.fit` loop; :class:`~torchrl_wbrm.training.WBRMTrainer` drives the same object from its
own loop (progress bar, logging, checkpoints). :func:`fit_density_ratio` is the one-call version.
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from tensordict.utils import NestedKey
from torchrl.data import ReplayBuffer

from torchrl_wbrm.keys import BEHAVIOUR, DENSITY_RATIO, EXPERT, HELD_OUT_LOSS, LOSS_DENSITY_RATIO
from torchrl_wbrm.data import PairedSampler, make_replay_buffer
from torchrl_wbrm.modules import DensityRatioNetwork
from torchrl_wbrm.objectives import RobustDensityRatioLoss

__all__ = ["CategoricalToOneHot", "DensityRatioFit", "DensityRatioFitter", "as_tensordict", "fit_density_ratio",
           "holdout_split"]


def as_tensordict(data: TensorDictBase | ReplayBuffer) -> TensorDictBase:
    """The samples of a TensorDict or of a replay buffer (its whole storage, ``buffer[:]``), one row per sample: a
    multi-dimensional batch (``[episodes, steps]``, a 2-d storage) is flattened to ``[N]``, a 1-d one returned as
    is."""
    if isinstance(data, ReplayBuffer):
        if len(data) == 0:
            raise ValueError("The replay buffer is empty.")
        data = data[:]
    elif not isinstance(data, TensorDictBase):
        raise TypeError(f"Expected a TensorDict or a torchrl ReplayBuffer, got {type(data).__name__}.")
    return data.reshape(-1) if data.batch_dims > 1 else data


class CategoricalToOneHot(nn.Module):
    """Categorical action indices (``[*B]``, or ``[*B, 1]`` with ``keepdim``) as one-hot rows ``[*B, num_actions]``
    (rows of an identity buffer, so they follow the network's dtype and device). :func:`fit_density_ratio` puts it
    in front of the ratio network it builds for index actions, so that network reads the data's own actions."""

    def __init__(self, num_actions: int, *, keepdim: bool = False) -> None:
        super().__init__()
        self.num_actions, self.keepdim = int(num_actions), bool(keepdim)
        self.register_buffer("eye", torch.eye(self.num_actions))

    def forward(self, action: torch.Tensor) -> torch.Tensor:
        index = action.squeeze(-1) if self.keepdim else action
        return self.eye[index.long()]

    def extra_repr(self) -> str:
        return f"num_actions={self.num_actions}, keepdim={self.keepdim}"


def _categorical_layout(behaviour: TensorDictBase, expert: TensorDictBase, num_actions: int | None,
                        ) -> tuple[int, bool] | None:
    """``(num_actions, keepdim)`` where both sets hold integer action indices (``[N]`` or ``[N, 1]``), else ``None``.
    ``num_actions`` defaults to the largest index seen plus one; an index outside ``[0, num_actions)`` is refused."""
    actions = [behaviour.get("action"), expert.get("action")]
    if not all(a is not None and not a.is_floating_point() and a.dtype != torch.bool for a in actions):
        return None
    layouts = {a.shape[1:] for a in actions}
    if layouts not in ({torch.Size([])}, {torch.Size([1])}):
        raise ValueError(f"Integer 'action' entries of shapes {[tuple(a.shape) for a in actions]}: categorical "
                         "actions must be one index per row in both sets, shape [N] or [N, 1] (one-hot rows: float).")
    low = min(int(a.min()) for a in actions)
    high = max(int(a.max()) for a in actions)
    n = high + 1 if num_actions is None else int(num_actions)
    if low < 0 or high >= n:
        raise ValueError(f"The 'action' indices run from {low} to {high}, outside [0, {n - 1}] for num_actions={n}.")
    return n, layouts == {torch.Size([1])}


def holdout_split(data: TensorDictBase, fraction: float, generator: torch.Generator | None = None, *,
                  name: str = "data"):
    """``(train, held_out)``: a random ``fraction`` of the rows of ``data`` (at least one) held out; ``name`` says
    which set it is in the error for fewer than 2 rows.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"x": torch.arange(10)}, [10])
        >>> train, held_out = holdout_split(td, 0.2, torch.Generator().manual_seed(0))
        >>> train.shape, held_out.shape
        (torch.Size([8]), torch.Size([2]))
    """
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"The held-out fraction must lie in (0, 1), got {fraction}.")
    n = data.shape[0] if data.batch_dims else 0
    if n < 2:
        raise ValueError(f"The {name} set has {n} sample(s): holding out a share of it for early stopping needs at "
                         "least 2 (and training on it at least 1 more); pass more samples, or explicit held-out sets "
                         "(holdout=(behaviour, expert)).")
    perm = torch.randperm(n, generator=generator)
    n_hold = max(1, int(round(fraction * n)))
    return data[perm[n_hold:]], data[perm[:n_hold]]


def _as_inputs(data: TensorDictBase, keys: Sequence[NestedKey], dtype: torch.dtype, name: str) -> TensorDictBase:
    """The ratio network's input ``keys`` of ``data``, floating entries in the network's ``dtype`` (float64 data
    for a float32 network are converted); a missing key is a KeyError naming the set."""
    missing = [key for key in keys if data.get(key, None) is None]
    if missing:
        raise KeyError(f"The {name} set lacks {missing}, input(s) of the ratio network (its in_keys are "
                       f"{list(keys)}); it holds {sorted(str(k) for k in data.keys(True, True))}.")
    data = data.select(*keys)
    if data.batch_dims > 1:  # [episodes, steps]: one row per sample
        data = data.reshape(-1)
    return data.apply(lambda x: x.to(dtype) if x.is_floating_point() and x.dtype != dtype else x)


@dataclass
class DensityRatioFit:
    """What :meth:`DensityRatioFitter.fit` returns.

    Attributes:
        network: the ratio network, holding its best held-out state.
        loss_module: the :class:`~torchrl_wbrm.objectives.RobustDensityRatioLoss` around it.
        best_loss: the best held-out loss; ``best_step``: the step it was reached at.
        steps_run: gradient steps taken (fewer than asked when early stopping stopped the fit).
        stopped_early: whether ``patience`` evaluations without improvement ended the fit.
        ratio_collapse: whether the fit failed (:attr:`DensityRatioFitter.ratio_collapse`): it only got worse,
            so the network's initial state is the one returned. A caller should then not trust ŵ (the trainer flags
            the run ``ratio_collapse``).
        ratio_worse_than_uniform: whether the returned network's held-out loss is above that of ŵ ≡ 1 on the same
            held-out sets (:attr:`DensityRatioFitter.ratio_worse_than_uniform`; the trainer flags the run
            ``ratio_worse_than_uniform``).
        verdict: :meth:`DensityRatioFitter.verdict`: both verdicts with their reasons and the held-out losses.
        diagnostics: the loss's figures on the held-out sets with the best network (``"held_out_loss"``,
            ``"density_ratio_behaviour_mean"`` — about 1 for a good fit —, ``"density_ratio_expert_mean"``,
            ``"density_ratio_ess"``, ...).
        history: one record per evaluation: ``step``, ``held_out_loss`` and the training batch's figures.
    """

    network: TensorDictModule
    loss_module: RobustDensityRatioLoss
    best_loss: float
    best_step: int | None
    steps_run: int
    stopped_early: bool
    diagnostics: dict[str, float]
    history: list[dict] = field(default_factory=list)
    ratio_collapse: bool = False
    ratio_worse_than_uniform: bool = False
    verdict: dict = field(default_factory=dict)


class DensityRatioFitter:
    r"""Fits a ratio network ŵ(x, a) ≈ dP^e/dP^b with the robust (Basu) loss, keeping the best held-out state.

    Args:
        loss_module (RobustDensityRatioLoss or TensorDictModule): the stage-1 loss, or a ratio network (wrapped in
            ``RobustDensityRatioLoss(network)``, the paper's α = ½).
        behaviour: behaviour state-actions S^b: a TensorDict or a torchrl replay buffer (its whole storage is read).
        expert: expert state-actions S^e, the same way.

    Keyword Args:
        batch_size (int): samples drawn from *each* set per step. Defaults to ``512``.
        optimizer (torch.optim.Optimizer, optional): defaults to ``Adam(lr=lr, weight_decay=weight_decay)`` over the
            loss's parameters.
        lr, weight_decay (float): the default optimiser's settings. Default to ``1e-3`` and ``0``.
        grad_clip (float, optional): max gradient norm per step (``None``: off).
        holdout_fraction (float): share of each set held out for early stopping. Defaults to ``0.1``.
        holdout (tuple of TensorDict, optional): explicit ``(behaviour, expert)`` held-out sets; then all of
            ``behaviour`` and ``expert`` are trained on and ``holdout_fraction`` is unused.
        generator (torch.Generator, optional): draws the held-out split (defaults to a generator seeded 0).
        patience (int): evaluations without an improvement of more than ``min_improvement`` before
            :meth:`evaluate` reports ``"stop"``. Defaults to ``5``.
        min_improvement (float): Defaults to ``1e-6``.
        device (torch.device, optional): where batches go; defaults to the loss's parameters' device.

    What the fit is worth is one rule, :meth:`verdict` (the trainer reads it, and flags the run with its ``"flags"``):
    ``ratio_collapse`` when the fit only got worse or the weights do not average about 1 over the behaviour data,
    ``ratio_worse_than_uniform`` when the state it hands on scores worse on the held-out sets than ŵ ≡ 1.

    The training sets live in two ``TensorDictReplayBuffer`` (``behaviour_buffer``, ``expert_buffer``); ``sampler``
    draws the paired batches ``TensorDict({"behaviour": ..., "expert": ...})`` and may be replaced by any object with
    a ``sample()`` returning such a batch. Only the ratio network's ``in_keys`` are kept.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_wbrm.modules import DensityRatioNetwork
        >>> from torchrl_wbrm.ratio import DensityRatioFitter
        >>> _ = torch.manual_seed(0)
        >>> def samples(n, scale):  # 1-d states; the expert acts close to a = -x, the behaviour policy noisily
        ...     x = torch.randn(n, 1)
        ...     return TensorDict({"observation": x, "action": -x + scale * torch.randn(n, 1)}, [n])
        >>> behaviour, expert = samples(2000, 1.0), samples(1000, 0.2)
        >>> fitter = DensityRatioFitter(DensityRatioNetwork(1, 1, num_cells=(32,)), behaviour, expert,
        ...                             batch_size=256, lr=1e-2)
        >>> fit = fitter.fit(steps=200, eval_every=20)
        >>> fit.best_loss < fitter.initial_loss  # ŵ ≡ 1 at the start
        True
        >>> w = fit.network(expert.select("observation", "action"))["density_ratio"]
        >>> bool(w.mean() > 1.5)  # the expert's state-actions are over-represented in its own data
        True
    """

    def __init__(
        self,
        loss_module: RobustDensityRatioLoss | TensorDictModule,
        behaviour: TensorDictBase | ReplayBuffer,
        expert: TensorDictBase | ReplayBuffer,
        *,
        batch_size: int = 512,
        optimizer: torch.optim.Optimizer | None = None,
        lr: float = 1e-3,
        weight_decay: float = 0.0,
        grad_clip: float | None = None,
        holdout_fraction: float = 0.1,
        holdout: tuple[TensorDictBase, TensorDictBase] | None = None,
        generator: torch.Generator | None = None,
        patience: int = 5,
        min_improvement: float = 1e-6,
        device: torch.device | str | None = None,
    ) -> None:
        if not isinstance(loss_module, RobustDensityRatioLoss):
            loss_module = RobustDensityRatioLoss(loss_module)
        if batch_size <= 0:
            raise ValueError(f"batch_size must be > 0, got {batch_size}.")
        if patience < 1:
            raise ValueError(f"patience must be >= 1, got {patience}.")
        self.loss_module = loss_module
        self.network = loss_module.ratio_network
        params = list(loss_module.parameters())
        self.device = torch.device(device) if device is not None else params[0].device
        self.optimizer = optimizer if optimizer is not None else torch.optim.Adam(
            params, lr=lr, weight_decay=weight_decay)
        self.grad_clip = grad_clip
        self.patience = int(patience)
        self.min_improvement = float(min_improvement)
        self.keys = list(self.network.in_keys)
        dtype = params[0].dtype
        b = _as_inputs(as_tensordict(behaviour), self.keys, dtype, "behaviour")
        e = _as_inputs(as_tensordict(expert), self.keys, dtype, "expert")
        if holdout is None:
            generator = generator if generator is not None else torch.Generator().manual_seed(0)
            b_train, b_hold = holdout_split(b, holdout_fraction, generator, name="behaviour")
            e_train, e_hold = holdout_split(e, holdout_fraction, generator, name="expert")
        else:
            (b_train, e_train) = (b, e)
            b_hold = _as_inputs(holdout[0], self.keys, dtype, "held-out behaviour")
            e_hold = _as_inputs(holdout[1], self.keys, dtype, "held-out expert")
            for name, data in (("behaviour", b_train), ("expert", e_train), ("held-out behaviour", b_hold),
                               ("held-out expert", e_hold)):
                if not data.batch_dims or data.shape[0] == 0:
                    raise ValueError(f"The {name} set is empty: the density-ratio fit needs samples in it.")
        self.behaviour_buffer = make_replay_buffer(b_train.select(*self.keys))
        self.expert_buffer = make_replay_buffer(e_train.select(*self.keys))
        self.batch_size = int(batch_size)
        self.sampler = PairedSampler(self.behaviour_buffer, self.expert_buffer, self.batch_size, keys=self.keys,
                                     device=self.device)  # gathered straight into preallocated device tensors
        self.holdout = TensorDict(
            {BEHAVIOUR: b_hold.select(*self.keys), EXPERT: e_hold.select(*self.keys)}, batch_size=[]
        ).to(self.device)
        self.num_steps = 0
        #: the early-stopping record: best held-out ``loss``, its ``step``, the network's ``state`` then, and
        #: ``bad``, the evaluations since the last improvement. It starts at the network's initial state (step 0)
        #: and its held-out loss, so a fit that only got worse returns the state it started from.
        self.best = {"loss": math.inf, "state": copy.deepcopy(self.network.state_dict()), "bad": 0, "step": 0}
        with torch.no_grad():
            initial = self.loss_module(self.holdout)[LOSS_DENSITY_RATIO].item()
        if math.isfinite(initial):
            self.best["loss"] = initial
        #: the held-out loss of the network's initial state (the reference the "only got worse" rule compares with)
        self.start_loss = initial
        #: the held-out loss of ŵ ≡ 1 on the same held-out sets (the reference of ``ratio_worse_than_uniform``)
        self.uniform_loss = self._uniform_loss()

    #: ŵ's mean over the behaviour data outside [1 / COLLAPSE_FACTOR, COLLAPSE_FACTOR] is a collapsed fit (a density
    #: ratio averages 1 over the behaviour data).
    COLLAPSE_FACTOR = 10.0
    #: A fit whose held-out loss never beat its start's and rose above it by more than this share of |start loss|
    #: (and at least :attr:`WORSENING_MIN`) only got worse. A fit that merely ties its start (data with little to
    #: learn: behaviour close to the expert) has not collapsed.
    WORSENING_SHARE = 0.25
    WORSENING_MIN = 0.1
    #: The handed-on state's held-out loss above ŵ ≡ 1's by more than this (float32 rounding of the loss's means) is
    #: worse than ŵ ≡ 1.
    UNIFORM_TOLERANCE = 1e-6

    @torch.no_grad()
    def _uniform_loss(self) -> float:
        """The loss of ŵ ≡ 1 on the held-out sets, computed by the loss's own divergence (its normalisation penalty is
        0 there: ŵ ≡ 1 averages 1)."""
        from torchrl_wbrm.objectives.robust_density_ratio import basu_power_divergence

        loss = self.loss_module
        dtype = next(iter(loss.parameters())).dtype
        ones = [torch.ones(self.holdout[side].shape[0], dtype=dtype) for side in (BEHAVIOUR, EXPERT)]
        return basu_power_divergence(*ones, alpha=loss.alpha, relative_beta=loss.relative_beta,
                                     non_negative_correction=loss.non_negative_correction).item()

    def verdict(self, weights: torch.Tensor | None = None) -> dict:
        """What the fit is worth, judged on the held-out sets: the one rule behind the ``ratio_collapse`` and
        ``ratio_worse_than_uniform`` flags (:class:`~torchrl_wbrm.training.WBRMTrainer` reads it, it does not judge
        for itself).

        * ``"collapse"``: the fit only got worse (no evaluation beat the held-out loss of the start, so the start is
          the state handed on, and the held-out loss rose above it by :attr:`WORSENING_SHARE`), or ``weights`` (ŵ over
          the behaviour data, raw) do not average within [1 / :attr:`COLLAPSE_FACTOR`, :attr:`COLLAPSE_FACTOR`];
          ``"reasons"`` says which, in words.
        * ``"worse_than_uniform"``: the best state (the one :meth:`best_network` hands on) has a held-out loss above
          that of ŵ ≡ 1 (:attr:`uniform_loss`) by more than :attr:`UNIFORM_TOLERANCE`; ``"worse_than_uniform_reason"``
          says by how much.

        ``"flags"`` lists the flag names raised; the held-out losses (start, ŵ ≡ 1, best, worst) and, with
        ``weights``, their mean and the shares at the network's bounds are given beside them.
        """
        best = self.best
        start, uniform = self.start_loss, self.uniform_loss
        worst = best.get("worst")
        improved = not math.isfinite(start) or best.get("step", 0) != 0
        out: dict = {}
        reasons = []
        if weights is not None:
            w = weights.detach().double().reshape(-1).cpu()
            mean = float(w.mean())
            out["mean_behaviour"] = mean
            bounds = getattr(self.network, "bounds", None)
            if bounds is not None:
                low, high = bounds
                out["at_lower_bound"] = float((w <= low * 1.001).double().mean())
                out["at_upper_bound"] = float((w >= high / 1.001).double().mean())
            if not 1 / self.COLLAPSE_FACTOR <= mean <= self.COLLAPSE_FACTOR:
                reasons.append(f"the mean of ŵ over D is {mean:.3g}, not about 1 (a density ratio averages 1 over the "
                               f"behaviour data)")
        margin = max(self.WORSENING_MIN, self.WORSENING_SHARE * abs(start)) if math.isfinite(start) else None
        if not improved and worst is not None and worst > start + margin:
            reasons.append(f"the fit only got worse: its held-out loss rose from {start:.4g} at the start to "
                           f"{worst:.4g} and never went below the start, so ŵ is the untrained one and the run is "
                           f"unweighted")
        handed_on = float(best["loss"])
        worse = math.isfinite(uniform) and not handed_on <= uniform + self.UNIFORM_TOLERANCE
        worse_reason = None
        if worse:
            worse_reason = (f"handed on ŵ (step {best.get('step', 0)}) whose held-out loss {handed_on:.6g} is above the "
                            f"{uniform:.6g} of ŵ ≡ 1 on the same held-out sets (weighting by it fits them worse than "
                            f"not weighting)")
        out.update({
            "start_held_out_loss": start,
            "uniform_held_out_loss": uniform,
            "best_held_out_loss": handed_on,
            "best_step": best.get("step"),
            "worst_held_out_loss": worst,
            "improved": improved,
            "collapse": bool(reasons),
            "reasons": reasons,
            "worse_than_uniform": worse,
            "worse_than_uniform_reason": worse_reason,
            "flags": [name for name, raised in (("ratio_collapse", bool(reasons)),
                                                ("ratio_worse_than_uniform", worse)) if raised],
        })
        return out

    @property
    def ratio_collapse(self) -> bool:
        """:meth:`verdict`'s ``"collapse"`` on the held-out sets (without the weights over the behaviour data, which
        only the caller has): the fit only got worse. :meth:`fit` also returns it in :class:`DensityRatioFit`."""
        return self.verdict()["collapse"]

    @property
    def ratio_worse_than_uniform(self) -> bool:
        """:meth:`verdict`'s ``"worse_than_uniform"``: the state handed on scores worse on the held-out sets than
        ŵ ≡ 1 (:attr:`uniform_loss`)."""
        return self.verdict()["worse_than_uniform"]

    @property
    def initial_loss(self) -> float:
        """The population loss of ŵ ≡ 1 (about where :class:`~torchrl_wbrm.modules.DensityRatioNetwork` starts):
        ``1 − (1 + 1/α)`` for the Basu loss, ``1`` for KL (:attr:`uniform_loss` is its value on the held-out sets)."""
        alpha = self.loss_module.alpha
        return 1.0 if alpha == "kl" else 1.0 - (1.0 + 1.0 / alpha)

    def step(self) -> dict[str, torch.Tensor]:
        """One gradient step on a paired batch; returns the loss's scalar figures (detached tensors)."""
        batch = self.sampler.sample()
        if batch.device != self.device:
            batch = batch.to(self.device)
        out = self.loss_module(batch)
        loss = out[LOSS_DENSITY_RATIO]
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.grad_clip:
            torch.nn.utils.clip_grad_norm_(self.loss_module.parameters(), self.grad_clip)
        self.optimizer.step()
        self.num_steps += 1
        return {k: v.detach() for k, v in out.items() if v.ndim == 0}

    @torch.no_grad()
    def held_out_figures(self) -> dict[str, float]:
        """The loss's figures on the held-out sets with the network's current state (``"held_out_loss"`` first)."""
        out = self.loss_module(self.holdout)
        figures = {HELD_OUT_LOSS: out[LOSS_DENSITY_RATIO].item()}
        figures.update({k: v.item() for k, v in out.items() if k != LOSS_DENSITY_RATIO and v.ndim == 0})
        return figures

    @torch.no_grad()
    def evaluate(self, step: int | None = None) -> dict:
        """Score the held-out sets, keep the network's state if it is the best so far, count patience.

        ``step`` (defaults to the steps taken) is recorded with a new best. Returns ``{"held_out_loss",
        "improved", "stop"}``; ``"stop"`` is ``True`` once ``patience`` evaluations in a row brought no improvement.
        A non-finite held-out loss never becomes the best (it counts as no improvement); the caller decides
        whether to stop on it (:meth:`fit` raises).
        """
        step = self.num_steps if step is None else int(step)
        held_out = self.loss_module(self.holdout)[LOSS_DENSITY_RATIO].item()
        best = self.best
        best["evaluations"] = best.get("evaluations", 0) + 1
        if math.isfinite(held_out):  # the worst held-out loss seen (the "only got worse" rule of verdict)
            best["worst"] = held_out if best.get("worst") is None else max(best["worst"], held_out)
        improved = held_out < best["loss"] - self.min_improvement
        if improved:
            best.update(loss=held_out, state=copy.deepcopy(self.network.state_dict()), bad=0, step=step)
        else:
            best["bad"] += 1
        return {HELD_OUT_LOSS: held_out, "improved": improved, "stop": best["bad"] >= self.patience}

    def best_network(self) -> TensorDictModule:
        """Load the best held-out state into the network (shared with the loss) and return the network."""
        self.network.load_state_dict(self.best["state"])
        return self.network

    def state_dict(self) -> dict:
        """Everything a resumed fit needs: the loss's and optimiser's states, the early-stopping record, the step."""
        return {
            "loss_module": self.loss_module.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "best": copy.deepcopy(self.best),
            "num_steps": self.num_steps,
        }

    def load_state_dict(self, state_dict: dict) -> None:
        self.loss_module.load_state_dict(state_dict["loss_module"])
        self.optimizer.load_state_dict(state_dict["optimizer"])
        self.best = copy.deepcopy(state_dict["best"])
        self.num_steps = int(state_dict.get("num_steps", 0))

    def fit(
        self,
        steps: int,
        *,
        eval_every: int = 100,
        callback: Callable[[int, dict], None] | None = None,
    ) -> DensityRatioFit:
        """Step until ``steps`` steps in all (continuing from :attr:`num_steps`) or early stopping, evaluating every
        ``eval_every`` steps and at the last one; end with the best held-out state loaded.

        ``callback(step, record)`` is called after each evaluation (``record``: the step's training figures and
        ``held_out_loss``). A non-finite held-out loss raises :class:`FloatingPointError`.
        """
        if eval_every <= 0:
            raise ValueError(f"eval_every must be > 0, got {eval_every}.")
        if isinstance(steps, bool) or not isinstance(steps, int) or steps <= 0:
            raise ValueError(f"steps must be a positive integer (gradient steps in all), got {steps!r}.")
        history, stopped = [], False
        while self.num_steps < steps:
            figures = self.step()
            step = self.num_steps
            if step % eval_every == 0 or step == steps:
                result = self.evaluate(step)
                record = {"step": step, **{k: float(v) for k, v in figures.items()},
                          HELD_OUT_LOSS: result[HELD_OUT_LOSS]}
                history.append(record)
                if callback is not None:
                    callback(step, record)
                if not math.isfinite(result[HELD_OUT_LOSS]):
                    raise FloatingPointError(f"The held-out density-ratio loss is {result[HELD_OUT_LOSS]} at "
                                             f"step {step}; lower the learning rate or clip the gradients.")
                if result["stop"]:
                    stopped = True
                    break
        network = self.best_network()
        verdict = self.verdict()
        return DensityRatioFit(
            network=network, loss_module=self.loss_module, best_loss=self.best["loss"],
            best_step=self.best.get("step"), steps_run=self.num_steps, stopped_early=stopped,
            diagnostics=self.held_out_figures(), history=history, ratio_collapse=verdict["collapse"],
            ratio_worse_than_uniform=verdict["worse_than_uniform"], verdict=verdict,
        )


def fit_density_ratio(
    behaviour: TensorDictBase | ReplayBuffer,
    expert: TensorDictBase | ReplayBuffer,
    ratio_network: TensorDictModule | None = None,
    *,
    steps: int = 1500,
    eval_every: int = 100,
    patience: int = 5,
    batch_size: int = 512,
    lr: float = 1e-3,
    weight_decay: float = 0.0,
    grad_clip: float | None = 10.0,
    holdout_fraction: float = 0.1,
    alpha: float | str = 0.5,
    bounds: tuple[float, float] = (1e-3, 1e3),
    num_cells: Sequence[int] = (128, 128),
    seed: int = 0,
    device: torch.device | str | None = None,
    num_actions: int | None = None,
    **loss_kwargs,
) -> DensityRatioFit:
    """Fit ŵ ≈ dP^e/dP^b on two datasets (TensorDicts or replay buffers of ``"observation"``, ``"action"``) and
    return the best held-out network with its diagnostics (:class:`DensityRatioFit`).

    Without a ``ratio_network`` a :class:`~torchrl_wbrm.modules.DensityRatioNetwork` with ``bounds`` and
    ``num_cells`` is built from the data's observation and action sizes. ``alpha`` and ``loss_kwargs`` go to
    :class:`~torchrl_wbrm.objectives.RobustDensityRatioLoss`. ``seed`` seeds everything random in the fit: the
    held-out split, the new network's initialisation and the training batches, under a forked torch generator (the
    caller's global random state is left as it was), so the same seed gives the same fit. Float64 data are
    converted to the network's dtype. The defaults are the recipe's stage 1 (``RatioConfig``).

    Any action kind: a float action ``[N, d]`` (continuous, or one-hot rows) is read as it is; integer categorical
    indices ``[N]`` or ``[N, 1]`` are one-hot encoded inside the network built here (a
    :class:`CategoricalToOneHot` in front of the :class:`~torchrl_wbrm.modules.DensityRatioNetwork`, so the
    returned network reads the data's index actions, e.g. in :func:`~torchrl_wbrm.ratio.store_density_ratio`), over
    ``num_actions`` actions (default: the largest index in either set plus one). Multi-dimensional sets
    (``[episodes, steps]`` TensorDicts or storages) are flattened to one row per sample.
    """
    if isinstance(steps, bool) or not isinstance(steps, int) or steps <= 0:
        raise ValueError(f"steps must be a positive integer (gradient steps in all), got {steps!r}.")
    devices = [torch.device(device).index or 0] if device is not None and torch.device(device).type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        torch.manual_seed(seed)
        if ratio_network is None:
            b = as_tensordict(behaviour)
            for key in ("observation", "action"):
                if b.get(key, None) is None:
                    raise KeyError(f"The behaviour set lacks {key!r}, needed to size the ratio network; pass a "
                                   "ratio_network reading the keys it holds.")
            categorical = _categorical_layout(b, as_tensordict(expert), num_actions)
            if categorical is None:
                ratio_network = DensityRatioNetwork(b["observation"].shape[-1], b["action"].shape[-1],
                                                    bounds=tuple(bounds), num_cells=tuple(num_cells))
            else:
                n, keepdim = categorical
                one_hot = TensorDictModule(CategoricalToOneHot(n, keepdim=keepdim), in_keys=["action"],
                                           out_keys=[("_one_hot", "action")])
                ratio_network = TensorDictSequential(
                    one_hot,
                    DensityRatioNetwork(b["observation"].shape[-1], n, bounds=tuple(bounds), num_cells=tuple(num_cells),
                                        in_keys=("observation", ("_one_hot", "action"))),
                    selected_out_keys=[DENSITY_RATIO],
                )
        if device is not None:
            ratio_network = ratio_network.to(device)
        loss = RobustDensityRatioLoss(ratio_network, alpha=alpha, **loss_kwargs)
        fitter = DensityRatioFitter(
            loss, behaviour, expert, batch_size=batch_size, lr=lr, weight_decay=weight_decay, grad_clip=grad_clip,
            holdout_fraction=holdout_fraction, generator=torch.Generator().manual_seed(seed), patience=patience,
            device=device,
        )
        return fitter.fit(steps, eval_every=eval_every)
