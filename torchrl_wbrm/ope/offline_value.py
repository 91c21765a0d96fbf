r"""A policy's value from logged data alone: fitted Q evaluation (FQE) on D, optionally ŵ-weighted, with a 95%
bootstrap interval over episodes. No environment is stepped.

The quantity is the one the online evaluation reports, the expected return of an episode from the data's initial
states with the policy acting deterministically:

- ``horizon=H`` (finite-horizon mode, the online evaluation's quantity): ``E_{x_0 ∼ D}[Σ_{t<H} γ^t r_t]``, the
  discounted return up to the episode's end (γ = 1: the undiscounted return, what the Minari and MountainCar
  evaluations report; LQR's is discounted, γ = 0.9, over H = 20 steps). Q reads the time left, ``(H − t) / H``,
  beside the observation, and an episode's end (``done``, truncation included) stops the bootstrap: the return
  ends there, as the online episode does.
- ``horizon=None``: the infinite-horizon discounted value ``E_{x_0 ∼ D}[V^π_γ(x_0)]`` (truncation bootstraps), the
  textbook FQE figure. It is not what a time-limited evaluation measures (the results:
  :doc:`/results/offline_value`).

The estimate is ``V̂ = mean_e Q̂(x_0^e, π(x_0^e))`` over D's episodes ``e``; its interval is the percentile bootstrap
of that mean over episodes (:func:`~torchrl_wbrm.evaluation.bootstrap_ci`). The interval covers the sampling of
the start states only, not the error of the fitted Q̂ (a refit on each resample would); the tests and
``docs/results/misspecified_q.md`` measure that error against exact answers.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import SoftUpdate

from torchrl_wbrm.evaluation.stats import bootstrap_ci
from torchrl_wbrm.keys import EPISODE
from torchrl_wbrm.modules import make_q_network
from torchrl_wbrm.objectives import FQELoss

__all__ = ["OfflineValue", "TIME_LEFT_KEY", "estimate_offline_value", "fit_fqe", "initial_rows", "value_at",
           "with_time_left"]

#: The entry Q reads the time left from, ``(H − t) / H``, in finite-horizon mode.
TIME_LEFT_KEY = "time_left"


@dataclass
class OfflineValue:
    """An offline estimate of a policy's value (see the module docstring for the quantity).

    Attributes:
        value: the estimate ``mean_e Q̂(x_0^e, π(x_0^e))``.
        low, high: its 95% percentile-bootstrap interval over episodes (start states only).
        episodes: the number of D's episodes (initial states) averaged.
        gamma: the discount; ``horizon``: H in finite-horizon mode, ``None`` for the infinite-horizon value.
        weighted: whether FQE was ŵ-weighted.
        quantity: the quantity in words.
        uses_environment: always ``False``: the estimate reads the datasets only.
        history: the FQE fit's mean loss every ``log_every`` steps.
    """

    value: float
    low: float
    high: float
    episodes: int
    gamma: float
    horizon: int | None
    weighted: bool
    quantity: str
    uses_environment: bool = False
    history: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


def _quantity(gamma: float, horizon: int | None) -> str:
    if horizon is None:
        return f"infinite-horizon discounted value (γ = {gamma:g}) from D's initial states"
    kind = "undiscounted" if gamma == 1.0 else f"discounted (γ = {gamma:g})"
    return f"{kind} return over episodes of at most {horizon} steps from D's initial states"


def _step_index(data: TensorDictBase) -> torch.Tensor:
    """Each row's step in its episode, ``[N]``: ``"step_count"`` where D holds it, else counted along contiguous
    ``"episode"`` ids."""
    step = data.get("step_count", None)
    if step is not None:
        return step.reshape(data.shape[0]).long()
    episode = data.get(EPISODE, None)
    if episode is None:
        raise KeyError("Finite-horizon FQE needs each row's step in its episode: D holds neither 'step_count' nor "
                       f"'episode' (it holds {sorted(str(k) for k in data.keys(True, True))}).")
    episode = episode.reshape(-1)
    start = torch.ones_like(episode, dtype=torch.bool)
    start[1:] = episode[1:] != episode[:-1]
    first = torch.cummax(torch.where(start, torch.arange(len(episode)), torch.zeros_like(episode)), 0).values
    return torch.arange(len(episode)) - first


def initial_rows(data: TensorDictBase) -> torch.Tensor:
    """The indices of D's episodes' first rows (step 0, or the first row of each contiguous ``"episode"`` id)."""
    rows = (_step_index(data) == 0).nonzero().squeeze(-1)
    if rows.numel() == 0:
        raise ValueError("D holds no episode's first row (step_count 0): there are no initial states to value.")
    return rows


def with_time_left(data: TensorDictBase, horizon: int, key: NestedKey = TIME_LEFT_KEY) -> TensorDictBase:
    """A shallow copy of ``data`` with ``key`` = ``(H − t) / H`` at ``x_t`` and ``(H − t − 1) / H`` at ``x'_t``, and
    ``("next", "terminated")`` set to ``("next", "done")``: in finite-horizon mode an episode's end, truncation
    included, ends the return."""
    if int(horizon) != horizon or horizon < 1:
        raise ValueError(f"horizon must be a positive integer (the evaluation's episode length), got {horizon!r}.")
    step = _step_index(data)
    if int(step.max()) >= horizon:
        raise ValueError(f"D holds a row at step {int(step.max())} of its episode, past horizon={horizon}: give the "
                         "evaluation's episode length (or None for the infinite-horizon value).")
    dtype = data.get("observation").dtype
    left = ((horizon - step).to(dtype) / horizon).unsqueeze(-1)
    out = data.copy()
    out.set(key, left)
    nxt = out.get("next").copy()
    nxt.set(key, left - 1.0 / horizon)
    nxt.set("terminated", nxt.get("done").clone())
    out.set("next", nxt)
    return out


def _default_q(data: TensorDictBase, gamma: float, horizon: int | None, num_cells: Sequence[int]) -> TensorDictModule:
    obs_dim, act_dim = data.get("observation").shape[-1], data.get("action").shape[-1]
    mean_reward = float(data.get(("next", "reward")).double().mean())
    if horizon is None:
        scale = 1.0 / (1.0 - gamma)
    else:
        scale = float(horizon) if gamma == 1.0 else (1.0 - gamma**horizon) / (1.0 - gamma)
    in_keys = ["observation", "action"] if horizon is None else ["observation", TIME_LEFT_KEY, "action"]
    extra = 0 if horizon is None else 1
    return make_q_network(obs_dim + extra, act_dim, num_cells=num_cells, activation="SiLU",
                          initial_bias=mean_reward * scale, in_keys=in_keys)


def fit_fqe(
    policy: TensorDictModule,
    data: TensorDictBase,
    *,
    gamma: float,
    horizon: int | None = None,
    q_network: TensorDictModule | None = None,
    weight_key: NestedKey | None = None,
    steps: int = 3000,
    batch_size: int = 256,
    lr: float = 1e-3,
    tau: float = 0.05,
    num_cells: Sequence[int] = (64, 64),
    seed: int = 0,
    log_every: int = 500,
) -> tuple[FQELoss, list]:
    """Fit ``Q ≈ Q^π`` on the transitions ``data`` with :class:`~torchrl_wbrm.objectives.FQELoss`: Adam on Q, a
    target copy moved by :class:`~torchrl.objectives.SoftUpdate` (``tau``), batches from a torchrl
    :class:`~torchrl.data.ReplayBuffer`. ``data`` must already hold the time left in finite-horizon mode
    (:func:`with_time_left`). ``weight_key``: ŵ-weighted FQE with the weights stored there. ``seed`` seeds the
    network's initialisation and the batches under a forked generator (the caller's random state is unchanged).
    Without ``q_network`` a SiLU MLP of ``num_cells`` starting at the data's mean reward times the horizon's
    discount sum is built. Returns the loss (Q is ``loss.value_network`` with ``loss.value_network_params``) and
    the mean loss every ``log_every`` steps; a non-finite loss is a RuntimeError naming the step."""
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}.")
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        q = _default_q(data, gamma, horizon, num_cells) if q_network is None else q_network
        loss = FQELoss(q, policy, use_weights=weight_key is not None)
        if weight_key is not None:
            loss.set_keys(weight=weight_key)
        loss.make_value_estimator(gamma=gamma)
        updater = SoftUpdate(loss, tau=tau)
        optimiser = torch.optim.Adam(loss.value_network_params.values(True, True), lr=lr)
        keys = list(dict.fromkeys([*loss.in_keys, ("next", "done")]))
        rows = data.select(*keys, strict=False)
        buffer = ReplayBuffer(storage=LazyTensorStorage(rows.shape[0]), batch_size=min(batch_size, rows.shape[0]),
                              generator=torch.Generator().manual_seed(seed))
        buffer.extend(rows)
        history, running = [], 0.0
        for step in range(1, steps + 1):
            value = loss(buffer.sample())["loss_value"]
            optimiser.zero_grad()
            value.backward()
            optimiser.step()
            updater.step()
            running += value.detach()
            if step % log_every == 0 or step == steps:
                mean = float(running) / (log_every if step % log_every == 0 else step % log_every)
                if not torch.isfinite(torch.tensor(mean)):
                    raise RuntimeError(f"FQE diverged: the loss is {mean} at step {step}.")
                history.append({"step": step, "loss": mean})
                running = 0.0
    return loss, history


@torch.no_grad()
def value_at(loss: FQELoss, states: TensorDictBase) -> torch.Tensor:
    """``Q̂(x, π(x))`` for each row of ``states`` (holding Q's state inputs and π's), shape ``[N]``."""
    states = states.copy()
    states.set(loss.tensor_keys.action, loss.policy_action(states))
    return loss.q_value(states)


def estimate_offline_value(
    policy: TensorDictModule,
    data: TensorDictBase,
    *,
    gamma: float,
    horizon: int | None,
    weight_key: NestedKey | None = None,
    level: float = 0.95,
    seed: int = 0,
    **fit_kwargs,
) -> OfflineValue:
    """The offline value of ``policy`` on the transitions ``data`` (D, with ``"step_count"`` or ``"episode"``):
    FQE (:func:`fit_fqe`, ``fit_kwargs`` passed on), then the mean of ``Q̂(x_0, π(x_0))`` over D's initial states with
    a percentile-bootstrap interval over episodes. ``horizon``: the evaluation's episode length (finite-horizon
    mode) or ``None`` (the infinite-horizon value). Reads ``data`` only; no environment is stepped."""
    if not 0.0 <= gamma <= 1.0 or (gamma == 1.0 and horizon is None):
        raise ValueError(f"gamma must lie in [0, 1], and below 1 without a horizon; got gamma={gamma!r}, "
                         f"horizon={horizon!r}.")
    prepared = data if horizon is None else with_time_left(data, horizon)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        loss, history = fit_fqe(policy, prepared, gamma=gamma, horizon=horizon, weight_key=weight_key, seed=seed,
                                **fit_kwargs)
        starts = prepared[initial_rows(prepared)]
        values = value_at(loss, starts)
    ci = bootstrap_ci(values, level=level, seed=seed)
    return OfflineValue(value=ci.mean, low=ci.low, high=ci.high, episodes=int(values.numel()), gamma=float(gamma),
                        horizon=horizon, weighted=weight_key is not None, quantity=_quantity(gamma, horizon),
                        history=history)
