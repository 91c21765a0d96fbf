"""``q.compile=true``: the Bellman-residual update's two losses through ``torch.compile``.

:class:`CompiledBellmanLosses` wraps a :class:`~torchrl_wbrm.objectives.WeightedBellmanLoss` and exposes the same
``value_loss(batch)`` and ``actor_loss(batch)`` (same figures, same keys), computed by two compiled tensor functions:
the networks are called with ``torch.func.functional_call`` on the loss's own (parameter-less) modules and its
``TensorDictParams``, so the optimisers, ``SoftUpdate``, checkpoints and ``state_dict`` are untouched, and
TorchInductor fuses the forward and backward of each loss. What stays eager: reading the batch's entries, the
sampled maximiser's uniform draws (drawn by torch's eager generator, so a compiled run draws what an eager one
draws), the optimiser step and the target update.

Differences from the eager loss: the per-batch input checks (finite values, non-negative weights) are not run (the
trainer's data are checked when they are built or loaded, and its divergence guard reads every step's loss), and
the fused kernels round differently, so losses agree with the eager ones to about 1e-6 relative, not bitwise
(tested to 1e-5). Supported: ``WeightedBellmanLoss`` itself (not subclasses such as MABO) with continuous actions,
the actor or sampled maximiser, the TD(0) target and ``reduction="mean"``; anything else raises ``ValueError``.

Compilation happens on the first call of each loss (the actor's at the first actor step); its wall time, execution
of that first step included, is kept in :attr:`CompiledBellmanLosses.compile_seconds`.
"""
from __future__ import annotations

import time
from contextlib import nullcontext

import torch
from torch.func import functional_call
from torchrl.objectives.value import TD0Estimator

from torchrl_wbrm.modules.maximisers import SampledActionMaximiser, uniform_actions
from torchrl_wbrm.objectives._fast import _entries
from torchrl_wbrm.objectives._utils import get_entry, per_sample
from torchrl_wbrm.objectives.weighted_bellman import WeightedBellmanLoss, _next

__all__ = ["CompiledBellmanLosses"]


def _named(params, prefix: str = "module.") -> dict:
    """``{name inside network.module: tensor}`` of a loss's TensorDictParams (or plain TensorDict)."""
    out = {}
    for name, value in _entries(params):
        if not name.startswith(prefix):
            raise ValueError(f"compile: parameter {name!r} is not under the network's module.")
        out[name[len(prefix):]] = value
    return out


class CompiledBellmanLosses:
    """``value_loss`` and ``actor_loss`` of ``loss`` as compiled tensor functions (see the module docstring).

    Args:
        loss: a ``WeightedBellmanLoss`` (continuous actions; its value estimator is built, TD(0)).

    Keyword Args:
        compile_kwargs: passed to ``torch.compile`` (e.g. ``{"mode": "max-autotune-no-cudagraphs"}``).
    """

    def __init__(self, loss: WeightedBellmanLoss, *, compile_kwargs: dict | None = None):
        if type(loss) is not WeightedBellmanLoss:
            raise ValueError(f"compile supports WeightedBellmanLoss itself, got {type(loss).__name__} (algo=wbrm, brm, fqi).")
        if loss._fast() is None:
            raise ValueError("compile needs continuous actions, the actor or sampled maximiser and plain "
                             "TensorDictModule networks (the losses' tensor path).")
        if type(loss.value_estimator) is not TD0Estimator or getattr(loss.value_estimator, "average_rewards", False):
            raise ValueError("compile supports the TD(0) target only.")
        if loss.reduction != "mean":
            raise ValueError(f"compile supports reduction='mean', got {loss.reduction!r}.")
        self.loss = loss
        self.compile_seconds = 0.0
        kwargs = {"dynamic": False, **(compile_kwargs or {})}
        self._value_fn = torch.compile(self._value_terms, **kwargs)
        self._actor_fn = torch.compile(self._actor_terms, **kwargs)
        self._first = {"value": True, "actor": True}
        keys = loss.tensor_keys
        self._q_keys = list(loss.value_network.in_keys)
        self._obs_keys = [k for k in self._q_keys if k != keys.action]
        self._actor_keys = list(loss.actor_network.in_keys) if loss.has_actor else []

    # ---------------------------------------------------------------- traced functions
    def _q(self, params: dict, inputs: list) -> torch.Tensor:
        return functional_call(self.loss.value_network.module, params, tuple(inputs))

    def _mu(self, params: dict, inputs: list) -> torch.Tensor:
        return functional_call(self.loss.actor_network.module, params, tuple(inputs))

    def _value_terms(self, q_params, next_q_params, next_actor_params, q_inputs, next_obs, next_actor_inputs,
                     extra_candidates, reward, terminated, weight, gamma):
        loss, action_key = self.loss, self.loss.tensor_keys.action
        batch = weight.shape
        q_value = self._q(q_params, q_inputs).reshape(batch)
        with torch.no_grad() if loss.delay_value else nullcontext():
            actor_action = None
            if loss.has_actor:
                with torch.no_grad():
                    actor_action = self._mu(next_actor_params, next_actor_inputs)
            if extra_candidates is not None:
                candidates = extra_candidates if actor_action is None else torch.cat(
                    [extra_candidates, actor_action.unsqueeze(0)], 0)
            else:
                candidates = actor_action.unsqueeze(0)
            k = candidates.shape[0]
            inputs, i = [], 0
            for key in self._q_keys:
                if key == action_key:
                    inputs.append(candidates)
                else:
                    inputs.append(next_obs[i].expand(k, *next_obs[i].shape))
                    i += 1
            next_value = self._q(next_q_params, inputs).squeeze(-1).max(0).values
        # torchrl's td0_return_estimate: r + γ · (~terminated).int() · V(x')
        target_value = (reward + gamma * (~terminated).int() * next_value.reshape(reward.shape)).reshape(batch)
        td_error = q_value - target_value
        if loss.residual == "squared":
            value = (weight * td_error.pow(2)).mean()
        else:
            value = (weight * td_error).mean().abs()
        with torch.no_grad():
            figures = {
                "td_error": td_error.pow(2),
                "td_error_mean": td_error.mean(),
                "td_error_abs_mean": td_error.abs().mean(),
                "q_mean": q_value.mean(),
                "target_value_mean": target_value.mean(),
            }
            if loss.use_weights:
                figures["weight_mean"] = weight.mean()
                figures["weight_ess"] = weight.sum().pow(2) / weight.pow(2).sum()
        return value, figures

    def _actor_terms(self, actor_params, q_params, actor_inputs, obs, action, weight):
        loss, action_key = self.loss, self.loss.tensor_keys.action
        batch = weight.shape
        mu = self._mu(actor_params, actor_inputs)
        inputs, i = [], 0
        for key in self._q_keys:
            if key == action_key:
                inputs.append(mu)
            else:
                inputs.append(obs[i])
                i += 1
        q_actor = self._q(q_params, inputs).reshape(batch)
        per_sample_loss = -q_actor
        figures = {"actor_q_mean": q_actor.detach().mean()}
        if loss.bc_alpha is not None:
            bc = (mu - action).pow(2).reshape(*batch, -1).mean(-1)
            lmbd = loss.bc_alpha / q_actor.abs().mean().detach().clamp_min(1e-6)
            per_sample_loss = lmbd * per_sample_loss + bc
            figures["bc_loss"] = bc.detach().mean()
        if loss.weight_actor_loss:
            per_sample_loss = per_sample_loss * weight
        return per_sample_loss.mean(), figures

    # ---------------------------------------------------------------- the loss's API
    def _weight(self, tensordict) -> torch.Tensor:
        loss = self.loss
        if not loss.use_weights:
            reward = get_entry(tensordict, _next(loss.tensor_keys.reward), "the reward")
            return torch.ones(tensordict.batch_size, device=reward.device, dtype=reward.dtype)
        key = loss.tensor_keys.weight
        weight = get_entry(tensordict, key, "the per-sample weight ŵ(x, a)")
        return per_sample(weight, tensordict.batch_size, key).detach()

    def _timed(self, name, fn, *args):
        if not self._first[name]:
            return fn(*args)
        start = time.perf_counter()
        out = fn(*args)
        self._first[name] = False
        self.compile_seconds += time.perf_counter() - start
        return out

    def value_loss(self, tensordict):
        """As :meth:`WeightedBellmanLoss.value_loss`: ``(loss, diagnostics)``."""
        loss, keys = self.loss, self.loss.tensor_keys
        batch = tensordict.batch_size
        next_td = get_entry(tensordict, "next", "the sub-TensorDict of next states")
        reward = get_entry(tensordict, _next(keys.reward), "the reward")
        done = get_entry(tensordict, _next(keys.done), "episode-end flag")
        terminated = tensordict.get(_next(keys.terminated), default=done)
        if terminated.dtype != torch.bool:
            terminated = terminated != 0
        if reward.shape == batch:  # torchrl's estimator works on [*B, 1]
            reward, terminated = reward.unsqueeze(-1), terminated.reshape(reward.shape + (1,))
        q_inputs = [get_entry(tensordict, k, "an input of the value network") for k in self._q_keys]
        next_obs = [get_entry(next_td, k, "a next-state input of the value network") for k in self._obs_keys]
        next_actor_inputs = [get_entry(next_td, k, "an input of the actor") for k in self._actor_keys]
        extra = None
        if isinstance(loss.maximiser, SampledActionMaximiser):
            m = loss.maximiser
            extra = uniform_actions(m.low, m.high, m.num_samples, batch)
        next_q = loss.target_value_network_params if loss.delay_value else loss.value_network_params
        estimator = loss.value_estimator
        if estimator.gamma.device != reward.device:
            estimator.gamma = estimator.gamma.to(reward.device)
        return self._timed(
            "value", self._value_fn, _named(loss.value_network_params), _named(next_q),
            _named(loss.target_actor_network_params) if loss.has_actor else {}, q_inputs, next_obs,
            next_actor_inputs, extra, reward, terminated.reshape(reward.shape), self._weight(tensordict),
            estimator.gamma,
        )

    def actor_loss(self, tensordict):
        """As :meth:`WeightedBellmanLoss.actor_loss`: ``(loss, diagnostics)``; only the actor gets gradients."""
        loss, keys = self.loss, self.loss.tensor_keys
        if not loss.has_actor:
            raise ValueError("actor_loss needs an actor_network; this loss was built without one.")
        actor_inputs = [get_entry(tensordict, k, "an input of the actor") for k in self._actor_keys]
        obs = [get_entry(tensordict, k, "an input of the value network") for k in self._obs_keys]
        action = get_entry(tensordict, keys.action, "the dataset action") if loss.bc_alpha is not None else None
        weight = self._weight(tensordict) if loss.weight_actor_loss else torch.ones(
            tensordict.batch_size, device=actor_inputs[0].device)
        q_params = {k: v.detach() for k, v in _named(loss.value_network_params).items()}
        return self._timed("actor", self._actor_fn, _named(loss.actor_network_params), q_params, actor_inputs, obs,
                           action, weight)
