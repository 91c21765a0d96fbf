r"""The exact value of a linear-Gaussian policy on an LQR system: ``V^π`` and ``Q^π`` in closed form.

For ``a = −M x + η``, ``η ∼ N(0, Σ_a)``, on ``x' = F x + G a + ξ``, ``ξ ∼ N(0, Σ_ξ)``, with the unclipped reward
``r = c_0 − x'Sx − a'Ra`` (the reward noise has mean 0), the infinite-horizon discounted values are quadratic:

.. math::

    V^\pi(x) = v_0 - x' P x, \qquad P = S + M'RM + \gamma A' P A, \quad A = F - GM,

    v_0 = \frac{c_0 - \operatorname{tr}(R\Sigma_a) - \gamma \operatorname{tr}(G'PG\,\Sigma_a)
          - \gamma \operatorname{tr}(P\Sigma_\xi)}{1 - \gamma},

    Q^\pi(x, a) = c_0 - x'Sx - a'Ra + \gamma\left(v_0 - \operatorname{tr}(P\Sigma_\xi)
                  - (Fx + Ga)' P (Fx + Ga)\right).

With ``M = K`` and ``Σ_a = 0`` these are :meth:`~torchrl_wbrm.envs.LQREnv.optimal_value` and
:meth:`~torchrl_wbrm.envs.LQREnv.optimal_q`; ``E_{x_0}[V^π(x_0)]`` is the limit of
:meth:`~torchrl_wbrm.envs.LQREnv.policy_return` (``clipped=False``) as the horizon grows (both tested). The clip
``max(r, 0)`` of the environment adds the expected excess where the cost passes ``c_0``: on the paper's systems it
is below 0.02 from ``x_0 ∼ N(0, I)`` and larger on states far from 0.
"""
from __future__ import annotations

import numpy as np
import torch

from torchrl_wbrm.envs import LQREnv

__all__ = ["linear_policy_q", "linear_policy_value"]


def linear_policy_value(env: LQREnv, gain, action_noise_std: float = 0.0, *, tol: float = 1e-12,
                        max_iter: int = 100_000) -> tuple[np.ndarray, float]:
    """``(P, v_0)`` of ``V^π(x) = v_0 − x'Px`` for ``a = −M x + N(0, σ² I)`` (float64), by the discounted Lyapunov
    fixed point. A gain that makes ``√γ (F − GM)`` unstable has no finite value: a ValueError."""
    cfg = env.config
    mats = cfg.matrices()
    F, G, R, S = mats["F"], mats["G"], mats["R"], mats["S"]
    M = np.asarray(torch.as_tensor(gain, dtype=torch.float64))
    if M.shape != (cfg.action_dim, cfg.state_dim):
        raise ValueError(f"gain must have shape ({cfg.action_dim}, {cfg.state_dim}), got {M.shape}.")
    A = F - G @ M
    if np.max(np.abs(np.linalg.eigvals(A))) * np.sqrt(cfg.gamma) >= 1.0:
        raise ValueError("The policy's closed loop F − GM grows faster than 1/√γ: its discounted value is infinite.")
    P = S.copy()
    base = S + M.T @ R @ M
    for _ in range(max_iter):
        P_new = base + cfg.gamma * A.T @ P @ A
        if np.max(np.abs(P_new - P)) < tol:
            P = P_new
            break
        P = P_new
    P = 0.5 * (P + P.T)
    sigma_a = float(action_noise_std) ** 2 * np.eye(cfg.action_dim)
    sigma_xi = cfg.transition_noise_std**2 * np.eye(cfg.state_dim)
    v0 = (cfg.reward_offset - np.trace(R @ sigma_a) - cfg.gamma * np.trace(G.T @ P @ G @ sigma_a)
          - cfg.gamma * np.trace(P @ sigma_xi)) / (1.0 - cfg.gamma)
    return P, float(v0)


def linear_policy_q(env: LQREnv, gain, action_noise_std: float, observation: torch.Tensor,
                    action: torch.Tensor) -> torch.Tensor:
    """``Q^π(x, a)`` of the policy ``a = −M x + N(0, σ² I)`` (unclipped reward, infinite horizon), shape ``[*, 1]``."""
    cfg = env.config
    P, v0 = linear_policy_value(env, gain, action_noise_std)
    mats = {k: torch.as_tensor(v).to(observation) for k, v in cfg.matrices().items()}
    P = torch.as_tensor(P).to(observation)
    mean_next = observation @ mats["F"].T + action @ mats["G"].T

    def quad(v, m):
        return ((v @ m) * v).sum(-1, keepdim=True)

    noise = cfg.transition_noise_std**2 * float(torch.trace(P))
    return (cfg.reward_offset - quad(observation, mats["S"]) - quad(action, mats["R"])
            + cfg.gamma * (v0 - noise - quad(mean_next, P)))
