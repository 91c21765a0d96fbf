"""Scores against the truth: returns, paired regret, Q* error, density-ratio error and effective sample size.

All evaluations run under ``set_exploration_type(DETERMINISTIC)`` and ``torch.no_grad()`` on fresh episodes with
their own seeds (never the training data).
"""
from __future__ import annotations


import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_wbrm._devices import device_of
from torchrl_wbrm.envs import LQRConfig, LQREnv, make_lqr_env
from torchrl_wbrm.evaluation.stats import MeanCI, mean_ci
from torchrl_wbrm.objectives.functional import effective_sample_size

__all__ = [
    "FiniteHorizonLQRPolicy",
    "discounted_returns",
    "evaluate_returns",
    "lqr_paired_regret",
    "q_error",
    "ratio_error",
]


class FiniteHorizonLQRPolicy(nn.Module):
    """The optimal finite-horizon LQR policy ``a_t = -K_t x_t`` (reads ``"observation"`` and ``"step_count"``)."""

    def __init__(self, env: LQREnv):
        super().__init__()
        self.register_buffer("gains", env.finite_horizon_gains().float())

    def forward(self, observation: torch.Tensor, step_count: torch.Tensor) -> torch.Tensor:
        t = step_count.reshape(observation.shape[:-1]).clamp_max(len(self.gains) - 1)
        return -torch.einsum("...ij,...j->...i", self.gains[t], observation)


def discounted_returns(rollout: TensorDictBase, gamma: float) -> torch.Tensor:
    """``sum_t gamma^t r_t`` along the last batch dimension of a ``[*, T]`` rollout (float64), up to each episode's end.

    Steps after an episode's first ``("next", "done")`` do not count: in a batched rollout with
    ``break_when_all_done=True`` an env that is done early is frozen and torchrl repeats its last transition (reward
    included) until all are done; with auto-reset they would belong to the next episode.
    """
    reward = rollout.get(("next", "reward")).squeeze(-1).double()
    discount = torch.as_tensor(gamma, dtype=torch.float64) ** torch.arange(reward.shape[-1], dtype=torch.float64)
    done = rollout.get(("next", "done"), None)
    if done is not None:
        done = done.reshape(reward.shape).long()
        reward = torch.where(done.cumsum(-1) - done > 0, torch.zeros_like(reward), reward)  # a done before t
    return (reward * discount).sum(-1)


def _cast_to(policy, env_device) -> dict:
    """``env.rollout``'s arguments for ``policy`` in an env on ``env_device``: a policy on another device (trained on
    an accelerator, acting in an env that steps on the CPU) gets torchrl's cast, each step's TensorDict moved to the
    policy's device and its action back; otherwise none."""
    policy_device = device_of(policy)
    if policy_device is None or env_device is None or policy_device == torch.device(env_device):
        return {}
    return {"auto_cast_to_device": True}


@torch.no_grad()
def evaluate_returns(env, policy, *, episodes: int, seed: int, gamma: float = 1.0, max_steps: int = 1000) -> MeanCI:
    """Mean return of ``policy`` (deterministic) over ``episodes`` fresh episodes, with a 95% CI.

    A batched env (batch ``[episodes]``) runs them all in one rollout; an unbatched env (gym) runs them one by one,
    each episode seeded with ``seed + i``.
    """
    returns = []
    cast = _cast_to(policy, env.device)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        if env.batch_size.numel() > 1:
            if env.batch_size.numel() != episodes:
                raise ValueError(f"A batched env must have batch size [episodes]={episodes}, got {env.batch_size}.")
            env.set_seed(seed)
            rollout = env.rollout(max_steps, policy, break_when_any_done=False, break_when_all_done=True,
                                  **cast)
            returns.append(discounted_returns(rollout, gamma))
        else:
            for i in range(episodes):
                env.set_seed(seed + i)
                rollout = env.rollout(max_steps, policy, **cast)
                returns.append(discounted_returns(rollout, gamma).reshape(1))
    return mean_ci(torch.cat(returns))


@torch.no_grad()
def lqr_paired_regret(
    experiment: str | LQRConfig, policy, *, episodes: int = 1000, seed: int = 0
) -> dict[str, MeanCI | float]:
    """Paired regret of ``policy`` against the exact optimal finite-horizon policy.

    Both run from the same start states with the same transition and reward noise (two copies of the env with one
    seed draw identical noise, whatever the actions), so the regret's standard error is tiny (~1e-4) compared with
    the spread of either return. Returns ``return`` (of the policy), ``regret``, ``optimal_return_paired`` (the
    optimum on the same episodes) and ``optimal_return_exact`` (:meth:`LQREnv.optimal_return`, a check of the
    paired run).
    """
    env_policy = make_lqr_env(experiment, batch_size=[episodes], seed=seed)
    env_optimal = make_lqr_env(experiment, batch_size=[episodes], seed=seed)
    base = env_policy.base_env
    horizon, gamma = base.config.horizon, base.config.gamma
    optimal = TensorDictModule(FiniteHorizonLQRPolicy(base), in_keys=["observation", "step_count"], out_keys=["action"])
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        ret_policy = discounted_returns(env_policy.rollout(horizon, policy, **_cast_to(policy, base.device)), gamma)
        ret_optimal = discounted_returns(env_optimal.rollout(horizon, optimal), gamma)
    return {
        "return": mean_ci(ret_policy),
        "regret": mean_ci(ret_optimal - ret_policy),
        "optimal_return_paired": mean_ci(ret_optimal),
        "optimal_return_exact": base.optimal_return(),
    }


@torch.no_grad()
def q_error(q_estimate: torch.Tensor, q_true: torch.Tensor) -> dict[str, float]:
    """Q-hat against Q*: ``relative_spread_error = RMS(Q-hat - Q*) / std(Q*)`` and ``bias = mean(Q-hat - Q*)``.

    The error is relative to Q*'s *spread*, not its size: where Q* varies little around a large mean (as on the LQR
    systems), a plain relative error ``|Q-hat - Q*| / |Q*|`` scores the constant Q = mean Q* near 0. ``centred_error``
    removes the bias as well.
    """
    q_estimate, q_true = q_estimate.double().reshape(-1), q_true.double().reshape(-1)
    if q_estimate.shape != q_true.shape:
        raise ValueError(f"Q-hat has {q_estimate.numel()} values, Q* has {q_true.numel()}.")
    diff = q_estimate - q_true
    spread = q_true.std()
    return {
        "relative_spread_error": (diff.pow(2).mean().sqrt() / spread).item(),
        "centred_error": ((diff - diff.mean()).pow(2).mean().sqrt() / spread).item(),
        "bias": diff.mean().item(),
        "q_true_mean": q_true.mean().item(),
        "q_true_std": spread.item(),
    }


@torch.no_grad()
def ratio_error(w_estimate: torch.Tensor, w_true: torch.Tensor | None = None) -> dict[str, float]:
    """Diagnostics of estimated ratios on behaviour samples, and their error when the true ratio is known.

    ``relative_l2 = sqrt(E_b (w-hat - w)^2) / sqrt(E_b w^2)``; ``mean_behaviour`` (should be about 1);
    ``ess`` and ``ess_fraction`` (Kish).
    """
    w_hat = w_estimate.double().reshape(-1)
    out = {
        "mean_behaviour": w_hat.mean().item(),
        "ess": effective_sample_size(w_hat).item(),
        "ess_fraction": effective_sample_size(w_hat).item() / w_hat.numel(),
        "max": w_hat.max().item(),
    }
    if w_true is not None:
        w = w_true.double().reshape(-1)
        out["relative_l2"] = ((w_hat - w).pow(2).mean().sqrt() / w.pow(2).mean().sqrt()).item()
        out["true_ess"] = effective_sample_size(w).item()
    return out
