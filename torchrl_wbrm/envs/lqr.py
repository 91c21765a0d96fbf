"""The linear-quadratic environment of the paper's Section 5.1, batched, with its exact solution.

Dynamics and reward (Section 5.1, "Linear Environment")::

    x_{t+1} = F x_t + G a_t + xi_t,                 xi_t ~ N(0, sigma_xi^2 I)
    r_t     = max(c0 - (x_t' S x_t + a_t' R a_t) + eps_t, 0),   eps_t ~ N(0, sigma_eps^2)

with ``c0 = 10``, ``S = I`` (the paper's ``x'x``), ``sigma_xi^2 = sigma_eps^2 = 0.01``, ``gamma = 0.9``,
``x_0 ~ N(0, I)`` and 20-step episodes (truncation, not termination: the system does not stop).

Because the system is linear-Gaussian, the project computes the truth instead of estimating it:

* :meth:`LQREnv.riccati` — the discounted infinite-horizon Riccati solution ``(P, K)``;
* :meth:`LQREnv.optimal_action`, :meth:`LQREnv.optimal_value`, :meth:`LQREnv.optimal_q` — closed forms of
  ``pi*``, ``V*`` and ``Q*`` for the *unclipped* reward (infinite horizon, discounted);
* :meth:`LQREnv.optimal_return` — the exact expected discounted ``horizon``-step return of the optimal
  finite-horizon (time-varying) policy from ``x_0 ~ N(0, I)``, with or without the clip at 0, by closed forms
  and a one-dimensional quadrature (no simulation);
* :meth:`LQREnv.policy_return` — the same for any linear-Gaussian policy ``a = -M x + N(0, Sigma_a)``;
* :meth:`LQREnv.state_action_covariances` — the per-step Gaussian laws of ``(x_t, a_t)`` under such a
  policy, from which :class:`LinearGaussianDensityRatio` computes true density ratios.

The action spec is bounded by ``LQRConfig.action_bound``: it is the domain learned policies act in (the
bounded actors and candidate maximisers read it). The dynamics do not clip actions, so the exact solution holds
for any action; the optimal action stays inside the default bound except with negligible probability.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Sequence

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded, Composite, Unbounded

from torchrl_wbrm.envs._batched import BatchedEpisodicEnv

__all__ = ["LQRConfig", "LQREnv", "LinearGaussianDensityRatio", "PAPER_EXPERIMENTS", "REWARD_CAP_87_84"]


def _diag(v: float, n: int = 2) -> list[list[float]]:
    return [[v if i == j else 0.0 for j in range(n)] for i in range(n)]


@dataclass
class LQRConfig:
    """Parameters of a linear-quadratic system (Section 5.1, Table 1 of the paper).

    Matrices are nested lists (so the dataclass is a valid Hydra structured config).

    Attributes:
        F: state transition matrix, ``d x d``.
        G: control matrix, ``d x m``.
        R: action cost, ``m x m``, symmetric positive definite.
        S: state cost, ``d x d``, symmetric positive semi-definite. The paper's ``x'x`` is ``S = I``.
        transition_noise_std: standard deviation of each coordinate of ``xi`` (paper: variance 0.01 -> 0.1).
        reward_offset: the constant ``c0`` in ``r = max(c0 - cost + eps, 0)`` (paper: 10).
        reward_clip: the floor of the reward (paper: 0). ``None`` disables the clip.
        reward_noise_std: standard deviation of ``eps`` (paper: variance 0.01 -> 0.1).
        gamma: discount factor (paper: 0.9). Used by the ground truth, not by the dynamics.
        horizon: episode length; episodes are truncated after this many steps (paper: 20).
        initial_std: ``x_0 ~ N(0, initial_std^2 I)`` (paper: 1).
        action_bound: the action spec is ``[-action_bound, action_bound]^m`` (not enforced by the dynamics).
    """

    F: list = field(default_factory=lambda: _diag(0.5))
    G: list = field(default_factory=lambda: _diag(0.5))
    R: list = field(default_factory=lambda: _diag(0.25))
    S: list = field(default_factory=lambda: _diag(1.0))
    transition_noise_std: float = 0.1
    reward_offset: float = 10.0
    reward_clip: float | None = 0.0
    reward_noise_std: float = 0.1
    gamma: float = 0.9
    horizon: int = 20
    initial_std: float = 1.0
    action_bound: float = 5.0

    def __post_init__(self):
        for name in ("F", "G", "R", "S"):
            try:
                matrix = np.asarray(getattr(self, name), dtype=np.float64)
            except (TypeError, ValueError) as err:
                raise ValueError(f"LQRConfig.{name} must be a matrix of numbers, got {getattr(self, name)!r}.") from err
            if not np.isfinite(matrix).all():
                raise ValueError(f"LQRConfig.{name} must be finite, got {matrix.tolist()}.")
        for name in ("transition_noise_std", "reward_offset", "reward_noise_std", "gamma", "initial_std", "action_bound"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"LQRConfig.{name} must be finite, got {getattr(self, name)!r}.")
        if self.reward_clip is not None and not math.isfinite(self.reward_clip):
            raise ValueError(f"LQRConfig.reward_clip must be finite or None, got {self.reward_clip!r}.")
        F, G, R, S = (np.asarray(m, dtype=np.float64) for m in (self.F, self.G, self.R, self.S))
        if F.ndim != 2 or F.shape[0] != F.shape[1]:
            raise ValueError(f"LQRConfig.F must be a square matrix, got shape {F.shape}.")
        d = F.shape[0]
        if G.ndim != 2 or G.shape[0] != d:
            raise ValueError(f"LQRConfig.G must have shape ({d}, m) to match F {F.shape}, got {G.shape}.")
        m = G.shape[1]
        if R.shape != (m, m):
            raise ValueError(f"LQRConfig.R must have shape ({m}, {m}) to match G {G.shape}, got {R.shape}.")
        if S.shape != (d, d):
            raise ValueError(f"LQRConfig.S must have shape ({d}, {d}) to match F {F.shape}, got {S.shape}.")
        if not np.allclose(R, R.T) or np.linalg.eigvalsh(R).min() <= 0:
            raise ValueError(f"LQRConfig.R must be symmetric positive definite, got {R.tolist()}.")
        if not np.allclose(S, S.T) or np.linalg.eigvalsh(S).min() < 0:
            raise ValueError(f"LQRConfig.S must be symmetric positive semi-definite, got {S.tolist()}.")
        if not 0.0 < self.gamma < 1.0:
            raise ValueError(f"LQRConfig.gamma must lie in (0, 1), got {self.gamma}.")
        if int(self.horizon) != self.horizon or self.horizon < 1:
            raise ValueError(f"LQRConfig.horizon must be a positive integer, got {self.horizon}.")
        for name in ("transition_noise_std", "reward_noise_std", "initial_std"):
            if getattr(self, name) < 0:
                raise ValueError(f"LQRConfig.{name} must be >= 0, got {getattr(self, name)}.")
        if self.action_bound <= 0:
            raise ValueError(f"LQRConfig.action_bound must be > 0, got {self.action_bound}.")

    @property
    def state_dim(self) -> int:
        return len(self.F)

    @property
    def action_dim(self) -> int:
        return len(self.G[0])

    def matrices(self) -> dict[str, np.ndarray]:
        """The system matrices as float64 numpy arrays."""
        return {k: np.asarray(getattr(self, k), dtype=np.float64) for k in ("F", "G", "R", "S")}

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


#: Table 1 of the paper.
PAPER_EXPERIMENTS: dict[str, LQRConfig] = {
    "exp1": LQRConfig(F=_diag(0.5), G=_diag(0.5), R=_diag(0.25)),
    "exp2": LQRConfig(F=_diag(0.6), G=_diag(0.4), R=_diag(0.16)),
    "exp3": LQRConfig(F=_diag(0.7), G=_diag(0.3), R=_diag(0.09)),
}

#: The paper's "theoretical maximum" 87.84 is the reward cap 10 * sum_{t<20} 0.9^t, not an attainable return.
REWARD_CAP_87_84 = 10.0 * sum(0.9**t for t in range(20))


def _solve_riccati(F, G, R, S, gamma, tol=1e-13, max_iter=100_000):
    """Discounted discrete-time Riccati fixed point: ``P = S + K'RK + gamma (F-GK)' P (F-GK)``."""
    P = S.copy()
    for _ in range(max_iter):
        K = gamma * np.linalg.solve(R + gamma * G.T @ P @ G, G.T @ P @ F)
        A = F - G @ K
        P_new = S + K.T @ R @ K + gamma * A.T @ P @ A
        if np.max(np.abs(P_new - P)) < tol:
            P = P_new
            break
        P = P_new
    else:  # pragma: no cover - only for unstabilisable systems
        raise RuntimeError("The discounted Riccati iteration did not converge: is (sqrt(gamma) F, G) stabilisable?")
    K = gamma * np.linalg.solve(R + gamma * G.T @ P @ G, G.T @ P @ F)
    return 0.5 * (P + P.T), K


def _finite_horizon_gains(F, G, R, S, gamma, horizon) -> list[np.ndarray]:
    """Time-varying gains ``K_t`` of the optimal ``horizon``-step policy (backward Riccati, ``P_T = 0``)."""
    P = np.zeros_like(S)
    gains = []
    for _ in range(horizon):
        K = gamma * np.linalg.solve(R + gamma * G.T @ P @ G, G.T @ P @ F)
        A = F - G @ K
        P = S + K.T @ R @ K + gamma * A.T @ P @ A
        gains.append(K)
    return gains[::-1]


def _expected_clip_excess(C: np.ndarray, offset: float, noise_std: float, n_quad: int = 512) -> float:
    """``E[max(Y - offset - eps, 0)]`` for ``Y = z' C z``, ``z ~ N(0, I_2)``, ``eps ~ N(0, noise_std^2)``.

    This is what the clip ``max(offset - Y + eps, 0)`` adds to the mean reward ``offset - E[Y]``. In two
    dimensions, with ``z = rho (cos u, sin u)``, ``rho^2 ~ Exp(mean 2)`` independent of ``u ~ U(0, 2 pi)`` and
    ``Y = rho^2 g(u)``, the exponential's memorylessness gives ``E[(rho^2 g - s)_+ | u] = 2 g exp(-s / (2 g))``,
    and the Gaussian ``eps`` integrates in closed form (a log-normal mean). What remains is a smooth periodic
    integral over ``u``, done by the trapezoidal rule (exponentially accurate). Exact up to the event
    ``offset + eps < 0`` (probability ``Phi(-offset / noise_std)``, about 1e-2000 for the paper's values).
    """
    lam = np.clip(np.linalg.eigvalsh(0.5 * (C + C.T)), 0.0, None)
    u = np.linspace(0.0, 2 * np.pi, n_quad, endpoint=False)
    g = lam[0] * np.cos(u) ** 2 + lam[1] * np.sin(u) ** 2
    g = np.maximum(g, 1e-300)
    vals = 2 * g * np.exp(-offset / (2 * g) + noise_std**2 / (8 * g**2))
    return float(vals.mean())


class LQREnv(BatchedEpisodicEnv):
    """A batched linear-quadratic system (Section 5.1 of the paper) as a TorchRL environment.

    Args:
        experiment (str or LQRConfig): ``"exp1"``, ``"exp2"``, ``"exp3"`` (Table 1 of the paper) or any
            :class:`LQRConfig`.

    Keyword Args:
        batch_size (int or sequence of int): number of independent systems stepped together. Defaults to ``()``.
        device: torch device. Defaults to CPU.
        seed (int, optional): seed of the environment's own generator (initial states, transition and reward
            noise). ``set_seed`` re-seeds it.
        dtype: floating dtype of observations, actions and rewards. Defaults to ``torch.float32``.

    Keys: ``"observation"`` (``d``), ``"action"`` (``m``), ``("next", "reward")`` (1),
    ``"done"``/``"terminated"``/``"truncated"`` (1; the system never terminates, it is truncated after
    ``horizon`` steps).

    Examples:
        >>> from torchrl.envs.utils import check_env_specs
        >>> env = LQREnv("exp1", batch_size=[1000], seed=0)
        >>> check_env_specs(env)
        >>> rollout = env.rollout(20, lambda td: td.set("action", env.optimal_action(td["observation"])))
        >>> rollout.shape
        torch.Size([1000, 20])
        >>> bool(rollout[:, -1]["next", "truncated"].all())
        True
        >>> round(env.optimal_return(), 3)  # exact, with the clip at 0
        85.435
    """

    def __init__(
        self,
        experiment: str | LQRConfig = "exp1",
        *,
        batch_size: int | Sequence[int] = (),
        device: torch.device | str | None = None,
        seed: int | None = None,
        dtype: torch.dtype = torch.float32,
    ):
        if isinstance(experiment, str):
            if experiment not in PAPER_EXPERIMENTS:
                raise ValueError(
                    f"Unknown LQR experiment {experiment!r}: expected one of {sorted(PAPER_EXPERIMENTS)} or an LQRConfig."
                )
            config = PAPER_EXPERIMENTS[experiment]
        elif isinstance(experiment, LQRConfig):
            config = experiment
        else:
            raise TypeError(f"experiment must be a str or an LQRConfig, got {type(experiment).__name__}.")
        super().__init__(batch_size=batch_size, device=device, seed=seed)
        self.config = config
        self._dtype = dtype
        mats = config.matrices()
        self._np = mats
        for name, value in mats.items():
            self.register_buffer(f"_{name}", torch.as_tensor(value, dtype=dtype, device=self.device))
        self._make_specs()

    # ------------------------------------------------------------------ specs and dynamics
    def _make_specs(self) -> None:
        d, m, bs = self.config.state_dim, self.config.action_dim, self.batch_size
        bound = self.config.action_bound
        self.observation_spec = Composite(
            observation=Unbounded(shape=(*bs, d), dtype=self._dtype, device=self.device), shape=bs
        )
        self.action_spec = Bounded(low=-bound, high=bound, shape=(*bs, m), dtype=self._dtype, device=self.device)
        self.reward_spec = Unbounded(shape=(*bs, 1), dtype=self._dtype, device=self.device)
        self._make_done_spec()

    def _randn(self, *shape) -> torch.Tensor:
        return torch.randn(*shape, generator=self.rng, device=self.device, dtype=self._dtype)

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        d = self.config.state_dim
        obs = self.config.initial_std * self._randn(*self.batch_size, d)
        return self._start_episodes(tensordict, obs)

    def _check_action(self, a: torch.Tensor | None, finite: bool = True) -> None:
        """The action of a step: present, of shape ``(*batch, m)``, of the env's dtype and (on CPU, unless
        ``finite=False``) finite."""
        expected = (*self.batch_size, self.config.action_dim)
        if a is None:
            raise KeyError(f"LQREnv.step needs an 'action' entry of shape {expected}.")
        if a.shape != expected:
            raise ValueError(f"LQREnv.step: 'action' has shape {tuple(a.shape)}, expected {expected} (batch {tuple(self.batch_size)}, "
                             f"action dim {self.config.action_dim}).")
        if a.dtype != self._dtype:
            raise TypeError(f"LQREnv.step: 'action' has dtype {a.dtype}, expected {self._dtype} (the env's dtype).")
        # a sum is finite iff every entry is (or it overflowed: then the entries are checked one by one); one
        # reduction instead of a bool tensor the size of the batch (a sixth of an LQR step at B = 16384)
        if finite and a.device.type == "cpu":
            self._check_finite(a)

    @staticmethod
    def _check_finite(a: torch.Tensor) -> None:
        if not bool(torch.isfinite(a.sum())) and not bool(torch.isfinite(a).all()):
            raise ValueError(f"LQREnv.step: 'action' holds {int((~torch.isfinite(a)).sum())} non-finite value(s) (NaN or inf).")

    def _dynamics(self, x: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(x_{t+1}, r_t)`` for a checked action: the reward noise is drawn first, then the transition noise."""
        cfg = self.config
        buffers = self._buffers  # (one dict lookup instead of four nn.Module.__getattr__ calls)
        S, R, F, G = buffers["_S"], buffers["_R"], buffers["_F"], buffers["_G"]
        cost = ((x @ S) * x).sum(-1, keepdim=True) + ((a @ R) * a).sum(-1, keepdim=True)
        reward = cfg.reward_offset - cost + cfg.reward_noise_std * self._randn(*self.batch_size, 1)
        if cfg.reward_clip is not None:
            reward = reward.clamp_min(cfg.reward_clip)
        next_x = x @ F.T + a @ G.T + cfg.transition_noise_std * self._randn(*x.shape)
        return next_x, reward

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        a = tensordict.get("action", None)
        self._check_action(a)
        next_x, reward = self._dynamics(tensordict.get("observation"), a)
        buffers = self._buffers
        step_count = buffers["_step_count"] + 1
        buffers["_step_count"] = step_count  # the registered buffer, replaced without nn.Module.__setattr__
        truncated = step_count >= self.config.horizon
        terminated = torch.zeros_like(truncated)
        return TensorDict(
            {
                "observation": next_x,
                "reward": reward,
                "done": truncated | terminated,
                "terminated": terminated,
                "truncated": truncated,
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    _FLAGS = ("done", "terminated", "truncated")

    def rollout(self, max_steps: int, policy=None, callback=None, **kwargs) -> TensorDictBase:
        """torchrl's :meth:`~torchrl.envs.EnvBase.rollout`; the common call (a TensorDict policy, a fresh reset,
        stop when done) takes a shorter path with the same result.

        ``env.rollout(n, policy)`` spends most of a small batch's time in ``EnvBase.step``'s generic bookkeeping
        (shape checks, done completion, ``"next"`` handling, ``step_mdp``). After a full reset every system is
        truncated at the same step and never terminates, so the done flags of the whole rollout are known in
        advance: ``False`` everywhere but ``("next", "done")`` and ``("next", "truncated")`` at step ``horizon - 1``.
        The shortcut therefore runs ``min(max_steps, horizon)`` steps of the policy, :meth:`_check_action` and
        :meth:`_dynamics` (the arithmetic and the generator draws of :meth:`_step`, in the same order), hands the
        policy what ``step_mdp`` would (the new observation, the previous action and the policy's other entries,
        ``False`` flags), stacks the float entries step by step and builds the flags in one allocation each. The
        output, the step counter and the generator state are those of torchrl's loop (tested). A policy that writes
        the flags it is given in place is refused (a ``RuntimeError``); one that replaces them gets them stacked.
        Any other argument (``break_when_any_done=False``, ``auto_reset=False``, a ``tensordict``, a callback,
        ``set_truncated``, an ``out``, a non-TensorDict policy, ...) runs torchrl's loop.
        """
        fast = (
            isinstance(policy, TensorDictModuleBase)
            and callback is None
            and set(kwargs) <= {"break_when_any_done", "break_when_all_done", "return_contiguous", "auto_reset"}
            and kwargs.get("break_when_any_done", None) in (None, True)
            and not kwargs.get("break_when_all_done", None)
            and kwargs.get("return_contiguous", False) in (None, True, False)
            and kwargs.get("auto_reset", True) is True
            and not self.run_type_checks
            and self._post_step_mdp_hooks is None
            and not self._has_dynamic_specs
            and type(self) is LQREnv  # a subclass may change a step: torchrl's loop
            and max_steps >= 1
        )
        if not fast:
            return super().rollout(max_steps, policy, callback, **kwargs)
        batch_size, device, flags = self.batch_size, self.device, self._FLAGS
        tensordict = self.reset()
        steps = min(int(max_steps), self.config.horizon)
        # the flags every step after the first hands the policy (the first gets the reset's own)
        given = {k: torch.zeros(*batch_size, 1, dtype=torch.bool, device=device) for k in flags}
        handed = [tensordict.get(k) for k in flags] + list(given.values())
        expected = [handed[:3]] + [handed[3:]] * (steps - 1)
        keys, columns = None, None
        next_observations, rewards = [], []
        for t in range(steps):
            out = policy(tensordict)
            if out is not tensordict:  # (updating a TensorDict with itself changes nothing)
                tensordict.update(out)
            entries, flat = self._leaves(tensordict)
            action = entries.get("action", None)
            self._check_action(action, finite=False)  # (finite: checked once on the stacked actions below)
            next_x, reward = self._dynamics(entries["observation"], action)
            if keys is None:
                keys, columns = list(entries), [[] for _ in entries]
            elif len(entries) != len(keys) or any(k not in entries for k in keys):  # other entries at some steps
                self._stack_mismatch(keys, list(entries))
            for column, key in zip(columns, keys):
                column.append(entries[key])
            next_observations.append(next_x)
            rewards.append(reward)
            # step_mdp: the root entries (the action and the policy's other outputs kept), the new observation and flags
            if not flat:
                entries = dict(tensordict.items())
            entries["observation"] = next_x
            entries.update(given)
            tensordict = TensorDict(entries, batch_size=batch_size, device=device)
        if bool(torch.cat(handed).any()):
            raise RuntimeError(
                "LQREnv.rollout: the policy wrote the done flags it was given in place; call "
                "EnvBase.rollout(env, max_steps, policy) for torchrl's loop."
            )
        self._buffers["_step_count"] = torch.full_like(self._buffers["_step_count"], steps)
        # torch.stack of the steps' TensorDicts, entry by entry (the same tensors, without its per-call checks)
        dim = len(batch_size)
        shape = (*batch_size, steps, 1)
        nested: dict = {}
        for key, column in zip(keys, columns):
            *parents, leaf = key if isinstance(key, tuple) else (key,)
            node = nested
            for parent in parents:
                node = node.setdefault(parent, {})
            if not parents and leaf in flags and all(c is e[flags.index(leaf)] for c, e in zip(column, expected)):
                node[leaf] = torch.zeros(shape, dtype=torch.bool, device=device)  # the flags it was handed, all False
            else:
                node[leaf] = torch.stack(column, dim)
        if nested["action"].device.type == "cpu":  # _check_action's finite check, for all steps at once
            self._check_finite(nested["action"])
        truncated = torch.zeros(shape, dtype=torch.bool, device=device)
        if steps >= self.config.horizon:
            truncated[..., -1, :] = True
        next_td = nested.setdefault("next", {})
        next_td.update(
            observation=torch.stack(next_observations, dim), reward=torch.stack(rewards, dim),
            done=truncated.clone(), terminated=torch.zeros(shape, dtype=torch.bool, device=device), truncated=truncated,
        )
        result = TensorDict(nested, batch_size=(*batch_size, steps), device=device)
        result.refine_names(..., "time")
        return result

    @staticmethod
    def _leaves(tensordict: TensorDictBase) -> tuple[dict, bool]:
        """``{key: tensor}`` of ``tensordict``'s leaves, the keys as ``keys(True, True)`` gives them, and whether
        they are its top-level entries (a plain TensorDict of tensors: its ``items()``)."""
        if type(tensordict) is TensorDict:
            entries = dict(tensordict.items())
            if all(type(v) is torch.Tensor for v in entries.values()):
                return entries, True
        return {key: tensordict.get(key) for key in tensordict.keys(True, True)}, False

    @staticmethod
    def _stack_mismatch(keys, step_keys):
        raise RuntimeError(
            f"The sets of keys in the tensordicts to stack are exclusive: a step wrote {sorted(map(str, step_keys))}, "
            f"the first step {sorted(map(str, keys))}."
        )

    # ------------------------------------------------------------------ exact solution
    def riccati(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Discounted infinite-horizon Riccati solution ``(P, K)`` (float64).

        ``V*(x) = v0 - x'Px`` and ``pi*(x) = -Kx`` maximise the discounted unclipped reward, with
        ``P = S + K'RK + gamma (F - GK)' P (F - GK)`` and ``K = gamma (R + gamma G'PG)^{-1} G'PF``.
        """
        if not hasattr(self, "_riccati_cache"):
            m = self._np
            self._riccati_cache = _solve_riccati(m["F"], m["G"], m["R"], m["S"], self.config.gamma)
        P, K = self._riccati_cache
        return torch.as_tensor(P), torch.as_tensor(K)

    def value_offset(self) -> float:
        """The constant ``v0`` of ``V*(x) = v0 - x'Px``: ``(c0 - gamma tr(P Sigma_xi)) / (1 - gamma)``."""
        P, _ = self.riccati()
        cfg = self.config
        trace = float(torch.trace(P)) * cfg.transition_noise_std**2
        return (cfg.reward_offset - cfg.gamma * trace) / (1 - cfg.gamma)

    def optimal_action(self, observation: torch.Tensor) -> torch.Tensor:
        """``pi*(x) = -Kx`` (the infinite-horizon discounted optimum)."""
        _, K = self.riccati()
        return -observation @ K.to(observation).T

    def optimal_value(self, observation: torch.Tensor) -> torch.Tensor:
        """``V*(x) = v0 - x'Px`` for the unclipped reward, infinite horizon, discounted. Shape ``(*, 1)``."""
        P, _ = self.riccati()
        P = P.to(observation)
        return self.value_offset() - ((observation @ P) * observation).sum(-1, keepdim=True)

    def optimal_q(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``Q*(x, a) = c0 - x'Sx - a'Ra + gamma E[V*(Fx + Ga + xi)]`` in closed form. Shape ``(*, 1)``.

        ``= v0 - x'Sx - a'Ra - gamma (Fx + Ga)' P (Fx + Ga)`` (unclipped reward, infinite horizon).
        """
        P, _ = self.riccati()
        F, G, R, S = (torch.as_tensor(self._np[k]) for k in "FGRS")  # float64: exact to the dtype of x
        P, F, G, R, S = (t.to(observation) for t in (P, F, G, R, S))
        mean_next = observation @ F.T + action @ G.T
        quad = lambda v, M: ((v @ M) * v).sum(-1, keepdim=True)  # noqa: E731
        return self.value_offset() - quad(observation, S) - quad(action, R) - self.config.gamma * quad(mean_next, P)

    def finite_horizon_gains(self, horizon: int | None = None) -> torch.Tensor:
        """Gains ``K_t`` (``t = 0..horizon-1``) of the optimal finite-horizon policy ``a_t = -K_t x_t``."""
        horizon = self.config.horizon if horizon is None else horizon
        m = self._np
        return torch.as_tensor(np.stack(_finite_horizon_gains(m["F"], m["G"], m["R"], m["S"], self.config.gamma, horizon)))

    def state_action_covariances(
        self, gain, action_noise_std, horizon: int | None = None, initial_std: float | None = None
    ) -> torch.Tensor:
        """Covariances ``C_t`` of ``(x_t, a_t)`` (zero mean) under ``a_t = -M_t x_t + N(0, Sigma_a)``.

        Args:
            gain: ``M`` as an ``m x d`` matrix, or ``horizon x m x d`` for a time-varying policy.
            action_noise_std: a float (isotropic) or an ``m``-vector of standard deviations.
            horizon: number of steps (defaults to the config's).
            initial_std: ``x_0 ~ N(0, initial_std^2 I)`` (defaults to the config's): another start distribution.

        Returns:
            a float64 tensor of shape ``(horizon, d + m, d + m)``.
        """
        horizon = self.config.horizon if horizon is None else horizon
        m_ = self._np
        F, G = m_["F"], m_["G"]
        d, m = self.config.state_dim, self.config.action_dim
        gains = np.asarray(torch.as_tensor(gain, dtype=torch.float64))
        if gains.ndim == 2:
            gains = np.broadcast_to(gains, (horizon, m, d))
        if gains.shape != (horizon, m, d):
            raise ValueError(f"gain must have shape ({m}, {d}) or ({horizon}, {m}, {d}), got {gains.shape}.")
        Sa = np.diag(np.broadcast_to(np.asarray(action_noise_std, dtype=np.float64) ** 2, (m,)))
        initial_std = self.config.initial_std if initial_std is None else initial_std
        if not (math.isfinite(initial_std) and initial_std > 0):
            raise ValueError(f"initial_std must be finite and > 0, got {initial_std!r}.")
        Sx = initial_std**2 * np.eye(d)
        noise = self.config.transition_noise_std**2 * np.eye(d)
        out = np.zeros((horizon, d + m, d + m))
        for t in range(horizon):
            M = gains[t]
            cross = -Sx @ M.T
            out[t, :d, :d] = Sx
            out[t, :d, d:] = cross
            out[t, d:, :d] = cross.T
            out[t, d:, d:] = M @ Sx @ M.T + Sa
            A = F - G @ M
            Sx = A @ Sx @ A.T + G @ Sa @ G.T + noise
        return torch.as_tensor(out)

    def policy_return(
        self, gain, action_noise_std=0.0, horizon: int | None = None, *, clipped: bool = True
    ) -> float:
        """Exact expected discounted ``horizon``-step return of ``a_t = -M_t x_t + N(0, Sigma_a)`` from ``x_0``.

        ``E[r_t] = c0 - tr((S + M_t'RM_t) Sigma_t) - tr(R Sigma_a)`` for the unclipped reward, where
        ``Sigma_t`` is the state covariance. With ``clipped=True`` the expected excess the clip at
        ``reward_clip`` adds is included exactly (two-dimensional ``(x, a)`` cost forms only, see
        :func:`_expected_clip_excess`); otherwise the figure is for the unclipped reward.
        """
        cfg = self.config
        R, S = self._np["R"], self._np["S"]
        d = cfg.state_dim
        covs = self.state_action_covariances(gain, action_noise_std, horizon).numpy()
        cost_matrix = np.zeros_like(covs[0])
        cost_matrix[:d, :d] = S
        cost_matrix[d:, d:] = R
        noisy = bool(np.any(np.asarray(action_noise_std, dtype=np.float64) != 0))
        total = 0.0
        for t, C in enumerate(covs):
            mean_reward = cfg.reward_offset - float(np.trace(cost_matrix @ C))
            if clipped and cfg.reward_clip is not None:
                mean_reward += self._clip_excess(C, cost_matrix, step=t, noisy=noisy)
            total += cfg.gamma**t * mean_reward
        return total

    def _clip_excess(self, C: np.ndarray, cost_matrix: np.ndarray, *, step: int = 0, noisy: bool = False) -> float:
        cfg = self.config
        if cfg.reward_clip != 0.0:
            raise NotImplementedError(f"The exact clipped return is implemented for reward_clip=0, got {cfg.reward_clip}.")
        # cost = z' L' W L z with z ~ N(0, I): the eigenvalues of W^(1/2) C W^(1/2) define the quadratic form.
        evals, evecs = np.linalg.eigh(C)
        root = evecs @ np.diag(np.sqrt(np.clip(evals, 0, None))) @ evecs.T
        form = root @ cost_matrix @ root
        lam = np.linalg.eigvalsh(0.5 * (form + form.T))
        lam = lam[lam > 1e-12 * max(lam.max(), 1e-300)]
        if len(lam) > 2:
            d, m = cfg.state_dim, cfg.action_dim
            if noisy:  # the action noise is a random direction of its own, beside the state's
                cause = (f"the action noise (action_noise_std > 0) makes a_t random beyond -M x_t, so (x_t, a_t) "
                         f"spans up to state_dim + action_dim = {d} + {m} dimensions; action_noise_std=0 keeps it "
                         f"at the state's {d}")
            else:
                cause = f"the state dimension is {d}"
            raise NotImplementedError(
                f"The exact clipped return needs the cost of (x_t, a_t) to have rank <= 2, got rank {len(lam)} at step "
                f"{step}: {cause}. Use clipped=False for the unclipped figure, or LQRConfig(reward_clip=None) "
                "(recipe: env.lqr.reward_clip=null) to train and score on the unclipped reward."
            )
        lam = np.pad(lam, (0, 2 - len(lam)))
        return _expected_clip_excess(np.diag(lam), cfg.reward_offset, cfg.reward_noise_std)

    def optimal_return(self, horizon: int | None = None, *, clipped: bool = True) -> float:
        """Exact expected discounted ``horizon``-step return of the optimal finite-horizon policy.

        The policy is the time-varying LQR policy ``a_t = -K_t x_t`` (backward Riccati with ``P_T = 0``), which
        is optimal for the unclipped reward. ``clipped=True`` (default) scores it on the env's clipped reward
        ``max(., 0)``, which is what a rollout measures (about +0.013 on the paper's systems, almost all at
        ``t = 0`` where ``x_0'x_0 > 10`` has probability ``e^{-5}``); ``clipped=False`` gives the unclipped figure.
        The reward noise has mean zero and enters only through the clip.
        """
        horizon = self.config.horizon if horizon is None else horizon
        return self.policy_return(self.finite_horizon_gains(horizon), 0.0, horizon, clipped=clipped)


class LinearGaussianDensityRatio(torch.nn.Module):
    """True density ratio between the state-action occupancies of two linear-Gaussian policies on an LQR system.

    A policy ``a = -M x + N(0, sigma^2 I)`` on a linear-Gaussian system gives zero-mean Gaussian laws
    ``N(0, C_t)`` of ``(x_t, a_t)`` at each step (:meth:`LQREnv.state_action_covariances`). The occupancy the
    datasets sample is the mixture ``sum_t p_t N(0, C_t)`` over ``t = 0..horizon-1``: ``time_weights="uniform"``
    (``p_t = 1/horizon``, every transition of every episode kept once: how this project's datasets are sampled)
    or ``"discounted"`` (``p_t ∝ gamma^t``, the normalised discounted occupancy of RL theory). The ratio is
    ``w(x, a) = p_expert(x, a) / p_behaviour(x, a)``, evaluated stably in log space. ``behaviour_initial_std``:
    the behaviour episodes start from ``N(0, behaviour_initial_std^2 I)`` instead of the system's start law (a shifted
    start distribution; the expert's keep the system's).

    Reads ``in_keys`` (``"observation"``, ``"action"``) and writes ``"density_ratio"`` when wrapped in a
    ``TensorDictModule``; :meth:`forward` takes the two tensors and returns ``(*batch, 1)``.
    """

    def __init__(
        self,
        env: LQREnv,
        expert_gain,
        expert_noise_std,
        behaviour_gain,
        behaviour_noise_std,
        *,
        time_weights: str = "uniform",
        horizon: int | None = None,
        behaviour_initial_std: float | None = None,
    ):
        super().__init__()
        horizon = env.config.horizon if horizon is None else horizon
        if time_weights == "uniform":
            p = torch.full((horizon,), 1.0 / horizon, dtype=torch.float64)
        elif time_weights == "discounted":
            p = env.config.gamma ** torch.arange(horizon, dtype=torch.float64)
            p = p / p.sum()
        else:
            raise ValueError(f"time_weights must be 'uniform' or 'discounted', got {time_weights!r}.")
        self.time_weights = time_weights
        self.register_buffer("log_p", p.log())
        for name, gain, std, start in (("expert", expert_gain, expert_noise_std, None),
                                       ("behaviour", behaviour_gain, behaviour_noise_std, behaviour_initial_std)):
            covs = env.state_action_covariances(gain, std, horizon, initial_std=start)
            eig = torch.linalg.eigvalsh(covs)
            if eig.min() <= 0:
                raise ValueError(
                    f"The {name} policy's state-action law is degenerate (smallest covariance eigenvalue "
                    f"{eig.min().item():.3g}): its action noise must be > 0 for a density ratio to exist."
                )
            self.register_buffer(f"{name}_precision", torch.linalg.inv(covs))
            self.register_buffer(f"{name}_logdet", torch.logdet(covs))

    def _log_mixture(self, z: torch.Tensor, precision: torch.Tensor, logdet: torch.Tensor) -> torch.Tensor:
        # z: (N, k); precision: (T, k, k). log sum_t p_t N(z; 0, C_t), dropping the common (2 pi)^(-k/2).
        maha = torch.einsum("ni,tij,nj->nt", z, precision, z)
        return torch.logsumexp(self.log_p - 0.5 * logdet - 0.5 * maha, dim=-1)

    def log_ratio(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        z = torch.cat([observation, action], -1).to(torch.float64)
        batch = z.shape[:-1]
        z = z.reshape(-1, z.shape[-1])
        log_w = self._log_mixture(z, self.expert_precision, self.expert_logdet) - self._log_mixture(
            z, self.behaviour_precision, self.behaviour_logdet
        )
        return log_w.reshape(*batch, 1)

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.log_ratio(observation, action).exp().to(observation.dtype)
