"""Computed reference points for the learning tests, and the recipe's own config for trainer-level tests.

Every learning threshold in the suite is derived from these figures, computed exactly, never typed in:

- :func:`reference_regrets`: the exact expected regret (against the exact optimal finite-horizon policy, on the
  env's clipped reward) of the zero action, of the behaviour policy's mean action ``a = −g K x`` and of the optimum
  itself (0), from :meth:`~torchrl_wbrm.envs.LQREnv.policy_return`. The trainer's paired regret estimates exactly
  this difference (same start states and noise for both policies).
- :func:`policy_q`: the exact Q of a linear-Gaussian policy (unclipped reward, infinite horizon, discounted, like
  :meth:`~torchrl_wbrm.envs.LQREnv.optimal_q`), so a Q̂ test can compare against what an estimator would reach if it
  merely evaluated the behaviour policy.
- :func:`compose_recipe`: ``configs/wbrm_offline.yaml`` composed by Hydra exactly as the recipe composes it, plus
  overrides (small budgets), so a trainer-level test follows the recipe's defaults whatever they become.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

from torchrl_wbrm.configs import CONFIG_DIR
from torchrl_wbrm.envs import LQRConfig, LQREnv

ROOT = Path(__file__).resolve().parents[1]


def lqr_env(experiment: str | LQRConfig) -> LQREnv:
    return LQREnv(experiment)


def reference_regrets(experiment: str | LQRConfig = "exp1", *, behaviour_gain_scale: float = 0.5) -> dict[str, float]:
    """Exact expected regrets: ``zero_action``, ``behaviour_mean`` (``a = −gain_scale·K x``, no noise), ``optimum``.

    ``optimum`` is the exact optimal finite-horizon policy scored against itself: 0 by construction; the stationary
    ``−Kx`` (``stationary_optimum``) is within 5e-4 of it.
    """
    env = lqr_env(experiment)
    _, K = env.riccati()
    best = env.optimal_return()
    return {
        "optimal_return": best,
        "zero_action": best - env.policy_return(torch.zeros_like(K)),
        "behaviour_mean": best - env.policy_return(behaviour_gain_scale * K),
        "stationary_optimum": best - env.policy_return(K),
        "optimum": 0.0,
    }


def policy_q(env: LQREnv, gain, noise_std: float):
    """``Q^π(x, a)`` of ``π: a = −M x + N(0, σ² I)`` (unclipped reward, infinite horizon, discounted), as a function.

    ``V^π(x) = v − x'Px`` with ``P = S + M'RM + γ (F − GM)'P(F − GM)`` and
    ``v = (c0 − tr(RΣa) − γ tr(P(GΣaG' + Σξ))) / (1 − γ)``; ``Q^π(x, a) = c0 − x'Sx − a'Ra + γ E V^π(Fx + Ga + ξ)``.
    With ``M = K`` and ``σ = 0`` it is :meth:`LQREnv.optimal_q` (tested).
    """
    cfg = env.config
    m = cfg.matrices()
    F, G, R, S = m["F"], m["G"], m["R"], m["S"]
    M = np.asarray(torch.as_tensor(gain, dtype=torch.float64))
    gamma, c0 = cfg.gamma, cfg.reward_offset
    A = F - G @ M
    P = S.copy()
    for _ in range(10_000):
        P_next = S + M.T @ R @ M + gamma * A.T @ P @ A
        if np.abs(P_next - P).max() < 1e-14:
            P = P_next
            break
        P = P_next
    Sa = noise_std**2 * np.eye(G.shape[1])
    Sxi = cfg.transition_noise_std**2 * np.eye(F.shape[0])
    v = (c0 - np.trace(R @ Sa) - gamma * np.trace(P @ (G @ Sa @ G.T + Sxi))) / (1 - gamma)
    F_, G_, R_, S_, P_ = (torch.as_tensor(t) for t in (F, G, R, S, P))

    def q(observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        x, a = observation.double(), action.double()
        mean_next = x @ F_.T + a @ G_.T
        quad = lambda z, W: ((z @ W) * z).sum(-1, keepdim=True)  # noqa: E731
        return c0 - quad(x, S_) - quad(a, R_) + gamma * (v - quad(mean_next, P_) - float(np.trace(P @ Sxi)))

    return q


def relative_q_error(q_hat: torch.Tensor, q_star: torch.Tensor) -> float:
    """``RMS(Q̂ − Q*) / std(Q*)``: the trainer's ``q_error_*`` figure (a constant Q scores about 1)."""
    q_hat, q_star = q_hat.double().reshape(-1), q_star.double().reshape(-1)
    return ((q_hat - q_star).pow(2).mean().sqrt() / q_star.std()).item()


def compose_recipe(*overrides: str, config_name: str = "wbrm_offline"):
    """The recipe's config (``configs/<config_name>.yaml``, its defaults list, the schema) with ``overrides``."""
    from hydra import compose, initialize_config_dir

    from torchrl_wbrm.training.config import register_configs

    register_configs()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose(config_name, overrides=[*overrides, "threads=1"])


#: the tiny LQR run of the run-directory, resume and trainer-stop tests: 2×16 networks, a few dozen steps
TINY_LQR = {
    "env": {"lqr_data": {"behaviour_episodes": 40, "expert_episodes": 20, "parallel_envs": 20}},
    "ratio": {"steps": 30, "batch_size": 64, "eval_every": 10, "num_cells": [16, 16]},
    "q": {"steps": 40, "batch_size": 32, "eval_every": 20, "num_cells": [16, 16], "actor_num_cells": [16, 16]},
    "eval": {"episodes": 50, "train_episodes": 20, "q_samples": 300, "offline_value": False},
    "logger": {"backend": "", "log_every": 5},
    "plots": False,
}


def tiny_lqr_config(*layers: dict, **overrides):
    """A ``WBRMConfig`` of :data:`TINY_LQR`, then each of ``layers`` (a test file's own base), then ``overrides``
    (sections as dicts, merged in that order: the last wins)."""
    from omegaconf import OmegaConf

    from torchrl_wbrm.training.config import WBRMConfig

    return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(WBRMConfig), TINY_LQR, *layers, overrides))


class Concat(nn.Module):
    """A linear layer on its inputs concatenated along the last dim: a Q or actor network with a known answer."""

    def __init__(self, linear: nn.Linear) -> None:
        super().__init__()
        self.linear = linear

    def forward(self, *inputs):
        return self.linear(torch.cat(inputs, -1))
