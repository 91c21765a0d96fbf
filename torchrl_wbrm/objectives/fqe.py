"""Fitted Q evaluation: the value ``Q^π`` of a given policy from logged transitions, optionally ŵ-weighted."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule, dispatch
from tensordict.utils import NestedKey
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives.common import LossModule
from torchrl.objectives.utils import ValueEstimators, dispatch_value_estimator
from torchrl.objectives.value import TD0Estimator

from torchrl_wbrm.keys import DENSITY_RATIO, PRIORITY_WEIGHT, WEIGHT_ESS
from torchrl_wbrm.objectives._fast import NetworkCall
from torchrl_wbrm.objectives._utils import check_not_empty, check_reduction, get_entry, per_sample
from torchrl_wbrm.objectives.functional import (
    bellman_residual,
    bellman_target,
    effective_sample_size,
    per_sample_weight,
    weighted_bellman_residual,
)

__all__ = ["FQELoss"]


def _next(key: NestedKey) -> tuple:
    return ("next", *key) if isinstance(key, tuple) else ("next", key)


class FQELoss(LossModule):
    r"""Fitted Q evaluation (Le, Voloshin & Yue, ICML 2019): ``Q ≈ Q^π`` of a *given* policy π from logged data.

    .. math::

        Y_i = r_i + \gamma\,(1 - \text{terminated}_i)\, Q_{\bar\theta}(x'_i, \pi(x'_i)), \qquad
        \ell_i = \left(Q_\theta(x_i, a_i) - Y_i\right)^2, \qquad
        L = \frac{\sum_i w_i\, \ell_i}{\sum_i w_i}

    ``Y`` is :func:`~torchrl_wbrm.objectives.functional.bellman_target` with π's action in place of the max, ``ℓ`` the
    squared form of :func:`~torchrl_wbrm.objectives.functional.weighted_bellman_residual` (per sample), and the
    batch is reduced as TorchRL's losses reduce a weighted batch (``LossModule._reduce_loss``): ``Σ wᵢ ℓᵢ / Σ wᵢ``,
    with rows dropped where ``("collector", "mask")`` or ``"shifted_valid"`` is False (see ``loss_mask_key``).
    ``wᵢ`` is ŵ(xᵢ, aᵢ) read from ``"density_ratio"`` when ``use_weights=True`` (ratio-weighted FQE: the data's
    state-actions reweighted toward another distribution, e.g. the expert's), times ``"priority_weight"`` where the
    batch holds one (TorchRL's convention, ``use_prioritized_weights``); with neither, the plain mean.

    The policy is fixed: it is called under ``torch.no_grad()`` and ``set_exploration_type(exploration_type)``
    (``DETERMINISTIC`` by default, the mode the online evaluation runs policies in). With ``RANDOM`` a stochastic
    policy draws one action per row, and the squared loss's minimiser is ``E_{a'∼π}[r + γ Q(x', a')]``, π's own
    (stochastic) value. Its parameters are held as the loss's ``policy_network_params`` and never get a gradient.

    Bootstrapping: ``delay_value=True`` (default) evaluates ``Q(x', π(x'))`` with a frozen copy of Q
    (``target_value_network_params``), updated outside the loss by :class:`~torchrl.objectives.SoftUpdate` or
    :class:`~torchrl.objectives.HardUpdate` (iterated FQE is ``HardUpdate`` every K steps); ``delay_value=False``
    bootstraps on the online parameters, detached (TorchRL's meaning of the flag). Truncation (``done`` without
    ``terminated``) bootstraps; termination does not. γ is set by ``make_value_estimator(gamma=...)`` (a
    :class:`~torchrl.objectives.value.TD0Estimator`; TorchRL's default 0.99 without the call).

    Args:
        value_network (TensorDictModule): Q, reading its in_keys (default ``"observation"``, ``"action"``) and
            writing ``"state_action_value"`` of shape ``[*B, 1]`` (or ``[*B]``).
        policy (TensorDictModule): π, reading the next state's entries among its in_keys and writing ``"action"``.

    Keyword Args:
        delay_value (bool): a frozen target copy of Q. Defaults to ``True``.
        use_weights (bool): read the per-sample weight ŵ from ``"density_ratio"`` (a missing entry is a
            KeyError). Defaults to ``False`` (plain FQE).
        use_prioritized_weights (bool or "auto"): read ``"priority_weight"`` where present (``"auto"``, default, or
            ``True``); ``False`` ignores it.
        exploration_type (ExplorationType): the mode π acts in. Defaults to ``ExplorationType.DETERMINISTIC``.
        reduction (str, optional): ``"mean"`` (default, also for ``None``), ``"sum"`` (``Σ wᵢ ℓᵢ``) or ``"none"``
            (``wᵢ ℓᵢ``, masked rows 0, shape ``[*B]``).

    Output: ``"loss_value"`` and the detached diagnostics ``"td_error_mean"``, ``"td_error_abs_mean"``,
    ``"q_mean"``, ``"target_value_mean"`` and, with weights, ``"weight_mean"`` and ``"weight_ess"``. ``forward``
    writes δ² (detached, ``[*B, 1]``) into the input under ``"td_error"``, as DQNLoss does; nothing else of the
    input changes.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.objectives import HardUpdate
        >>> from torchrl_wbrm.modules import make_q_network
        >>> from torchrl_wbrm.objectives import FQELoss
        >>> q = make_q_network(2, 1, initial_bias=0.0, num_cells=(16,))
        >>> policy = TensorDictModule(torch.nn.Linear(2, 1), in_keys=["observation"], out_keys=["action"])
        >>> loss = FQELoss(q, policy, use_weights=True)
        >>> loss.make_value_estimator(gamma=0.9)
        >>> updater = HardUpdate(loss, value_network_update_interval=100)
        >>> n = 8
        >>> data = TensorDict({
        ...     "observation": torch.randn(n, 2), "action": torch.randn(n, 1),
        ...     "density_ratio": torch.rand(n, 1),
        ...     ("next", "observation"): torch.randn(n, 2), ("next", "reward"): torch.randn(n, 1),
        ...     ("next", "done"): torch.zeros(n, 1, dtype=torch.bool),
        ...     ("next", "terminated"): torch.zeros(n, 1, dtype=torch.bool),
        ... }, [n])
        >>> out = loss(data)
        >>> out["loss_value"].backward()
        >>> updater.step()
        >>> data["td_error"].shape
        torch.Size([8, 1])
    """

    @dataclass
    class _AcceptedKeys:
        """Maintains default values for all configurable tensordict keys.

        Attributes:
            action (NestedKey): The data's action, and where the policy writes its action. Defaults to
                ``"action"``.
            state_action_value (NestedKey): Where Q writes Q(x, a). Defaults to ``"state_action_value"``.
            weight (NestedKey): The per-sample weight ŵ(x, a) (``use_weights=True``). Defaults to
                ``"density_ratio"``.
            priority_weight (NestedKey): TorchRL's per-sample (importance) weight, multiplied with ŵ when present.
                Defaults to ``"priority_weight"``.
            priority (NestedKey): Where δ² is written back. Defaults to ``"td_error"``.
            reward (NestedKey): The reward, read under ``"next"``. Defaults to ``"reward"``.
            done (NestedKey): The done flag, read under ``"next"``. Defaults to ``"done"``.
            terminated (NestedKey): The termination flag, read under ``"next"``: no bootstrap where True.
                Defaults to ``"terminated"``.
        """

        action: NestedKey = "action"
        state_action_value: NestedKey = "state_action_value"
        weight: NestedKey = DENSITY_RATIO
        priority_weight: NestedKey = PRIORITY_WEIGHT
        priority: NestedKey = "td_error"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    default_value_estimator = ValueEstimators.TD0
    SUPPORTED_VALUE_ESTIMATORS = (ValueEstimators.TD0,)

    value_network: TensorDictModule
    value_network_params: TensorDictParams
    target_value_network_params: TensorDictParams
    policy_network: TensorDictModule
    policy_network_params: TensorDictParams
    target_policy_network_params: TensorDictParams

    def __init__(
        self,
        value_network: TensorDictModule,
        policy: TensorDictModule,
        *,
        delay_value: bool = True,
        use_weights: bool = False,
        use_prioritized_weights: str | bool = "auto",
        exploration_type: ExplorationType = ExplorationType.DETERMINISTIC,
        reduction: str | None = None,
    ) -> None:
        reduction = check_reduction(reduction)
        if use_prioritized_weights not in (True, False, "auto"):
            raise ValueError(f"use_prioritized_weights must be True, False or 'auto', got {use_prioritized_weights!r}.")
        if not isinstance(exploration_type, ExplorationType):
            raise ValueError(f"exploration_type must be a torchrl ExplorationType, got {exploration_type!r}.")
        for name, module in (("value_network", value_network), ("policy", policy)):
            if not hasattr(module, "in_keys") or not hasattr(module, "out_keys"):
                raise TypeError(f"FQELoss: {name} must be a TensorDictModule (with in_keys and out_keys), got "
                                f"{type(module).__name__}.")
        self._in_keys = None
        super().__init__()
        self.delay_value = bool(delay_value)
        self.use_weights = bool(use_weights)
        self.use_prioritized_weights = use_prioritized_weights
        self.exploration_type = exploration_type
        self.reduction = reduction
        self.convert_to_functional(value_network, "value_network", create_target_params=self.delay_value)
        self.convert_to_functional(policy, "policy_network", create_target_params=False)
        for param in self.policy_network_params.values(True, True):  # π is given, never trained (nor soft-updated)
            param.requires_grad_(False)

    # ---------------------------------------------------------------- keys and value estimator
    def _forward_value_estimator_keys(self, **kwargs) -> None:
        if self._value_estimator is not None:
            self._value_estimator.set_keys(
                value=self.tensor_keys.state_action_value, reward=self.tensor_keys.reward,
                done=self.tensor_keys.done, terminated=self.tensor_keys.terminated,
            )
        self._in_keys = None

    def make_value_estimator(self, value_type: ValueEstimators | None = None, **hyperparams) -> None:
        """The TD(0) target ``r + γ (1 − terminated) Q(x', π(x'))``; set γ here (a finite number in [0, 1])."""
        if "gamma" in hyperparams:
            try:
                gamma = float(hyperparams["gamma"])
            except (TypeError, ValueError):
                raise ValueError(f"gamma must be a number in [0, 1], got {hyperparams['gamma']!r}.") from None
            if not (math.isfinite(gamma) and 0.0 <= gamma <= 1.0):
                raise ValueError(f"gamma must be a finite number in [0, 1] (the discount), got {hyperparams['gamma']!r}.")
        value_type = self.default_value_estimator if value_type is None else value_type
        if value_type not in self.SUPPORTED_VALUE_ESTIMATORS:
            raise NotImplementedError(f"FQELoss computes the TD(0) target only, got {value_type!r}.")
        dispatch_value_estimator(
            self, value_type, supported=self.SUPPORTED_VALUE_ESTIMATORS,
            tensor_keys={"value": self.tensor_keys.state_action_value, "reward": self.tensor_keys.reward,
                         "done": self.tensor_keys.done, "terminated": self.tensor_keys.terminated},
            value_network=None, **hyperparams,
        )
        if not isinstance(self._value_estimator, TD0Estimator) or self._value_estimator.average_rewards:
            self._value_estimator = None
            raise ValueError("FQELoss needs a TD0Estimator without average_rewards.")

    @property
    def _observation_keys(self) -> list[NestedKey]:
        return [key for key in self.value_network.in_keys if key != self.tensor_keys.action]

    @property
    def in_keys(self) -> list[NestedKey]:
        if self._in_keys is None:
            keys = [*self.value_network.in_keys, _next(self.tensor_keys.reward), _next(self.tensor_keys.done),
                    _next(self.tensor_keys.terminated), *[_next(k) for k in self._observation_keys],
                    *[_next(k) for k in self.policy_network.in_keys]]
            if self.use_weights:
                keys.append(self.tensor_keys.weight)
            self._in_keys = list(dict.fromkeys(keys))
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values):
        self._in_keys = values

    @property
    def out_keys(self) -> list[str]:
        keys = ["loss_value", "td_error_mean", "td_error_abs_mean", "q_mean", "target_value_mean"]
        return keys + (["weight_mean", WEIGHT_ESS] if self.use_weights else [])

    # ---------------------------------------------------------------- pieces
    def _network_call(self, name: str) -> NetworkCall:
        """How the loss calls ``"value_network"`` or ``"policy_network"``: a
        :class:`~torchrl_wbrm.objectives._fast.NetworkCall` (the module on tensors for a plain TensorDictModule,
        TorchRL's ``to_module`` call otherwise), cached per network (``_cache*``: dropped on ``.to()``)."""
        network = getattr(self, name)
        calls = self.__dict__.setdefault("_cache_network_calls", {})
        entry = calls.get(name)
        if entry is None or entry[0] is not network:
            out_key = self.tensor_keys.state_action_value if name == "value_network" else self.tensor_keys.action
            call = NetworkCall(network, getattr(self, f"{name}_params"), out_key,
                               why=f"the {name.replace('_', ' ')}'s output")
            entry = calls[name] = (network, call)
        return entry[1]

    def _q(self, params, inputs: dict, batch_size: torch.Size, *, detach: bool = False) -> torch.Tensor:
        """Q with ``params`` on ``inputs`` (Q's in_keys -> tensors), shape ``[*B]``."""
        out = self._network_call("value_network")(params, inputs, batch_size, detach=detach)
        return per_sample(out, batch_size, self.tensor_keys.state_action_value)

    def policy_action(self, tensordict: TensorDictBase) -> torch.Tensor:
        """π's action on the states of ``tensordict`` (its in_keys read there), without gradient, in the loss's
        exploration mode."""
        inputs = {k: get_entry(tensordict, k, "an input of the policy") for k in self.policy_network.in_keys}
        with torch.no_grad(), set_exploration_type(self.exploration_type):
            return self._network_call("policy_network")(self.policy_network_params, inputs, tensordict.batch_size,
                                                        detach=True)

    def next_state_value(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``Q(x', π(x'))``, shape ``[*B]``, detached: the target parameters (``delay_value``) or the online ones."""
        next_td = get_entry(tensordict, "next", "the sub-TensorDict of next states")
        inputs = {k: get_entry(next_td, k, "a next-state input of the value network") for k in self._observation_keys}
        inputs[self.tensor_keys.action] = self.policy_action(next_td)
        params = self.target_value_network_params if self.delay_value else self.value_network_params
        with torch.no_grad():
            return self._q(params, inputs, next_td.batch_size, detach=True)

    @torch.no_grad()
    def q_value(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``Q(x, a)`` with the online parameters at the entries of ``tensordict`` (Q's in_keys), shape ``[*B]``, no
        gradient: the fitted ``Q̂^π`` read back."""
        inputs = {k: get_entry(tensordict, k, "an input of the value network") for k in self.value_network.in_keys}
        return self._q(self.value_network_params, inputs, tensordict.batch_size, detach=True)

    def _weight(self, tensordict: TensorDictBase, dtype: torch.dtype) -> torch.Tensor | None:
        priority = self.tensor_keys.priority_weight
        reads_priority = self.use_prioritized_weights in (True, "auto") and not (
            self.use_weights and priority == self.tensor_keys.weight)
        return per_sample_weight(
            tensordict, self.tensor_keys.weight if self.use_weights else None, priority if reads_priority else None,
            dtype=dtype, why="the per-sample weight ŵ(x, a) of weighted FQE: write it there, or build the loss with "
                             "use_weights=False")

    def bellman_error(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """``(Q(x_i, a_i), Y_i)``, each ``[*B]``, with ``Y_i = r_i + γ (1 − terminated_i) Q(x'_i, π(x'_i))``."""
        batch = tensordict.batch_size
        check_not_empty(batch, "FQE")
        inputs = {k: get_entry(tensordict, k, "an input of the value network") for k in self.value_network.in_keys}
        q_value = self._q(self.value_network_params, inputs, batch)
        estimator = self.value_estimator
        reward_key = _next(self.tensor_keys.reward)
        reward = per_sample(get_entry(tensordict, reward_key, "the reward"), batch, reward_key)
        done_key, terminated_key = _next(self.tensor_keys.done), _next(self.tensor_keys.terminated)
        terminated = tensordict.get(terminated_key, None)
        if terminated is None:
            terminated = get_entry(tensordict, done_key, "the episode-end flag (no terminated entry either)")
        terminated = per_sample(terminated, batch, terminated_key).bool()
        gamma = estimator.gamma.to(reward.device)
        target = bellman_target(reward, self.next_state_value(tensordict).to(reward.dtype), terminated, gamma)
        return q_value, target

    def value_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The FQE loss (see the class docstring) and its diagnostics, including the per-sample δ² under
        ``"td_error"``."""
        q_value, target = self.bellman_error(tensordict)
        weight = self._weight(tensordict, q_value.dtype)
        squared = weighted_bellman_residual(q_value, target, q_value.new_ones(()), residual="squared",
                                            reduction="none")
        loss = self._reduce_loss(squared, tensordict, weights=weight)
        with torch.no_grad():
            td_error = bellman_residual(q_value, target)
            diagnostics = {"td_error": td_error.pow(2), "td_error_mean": td_error.mean(),
                           "td_error_abs_mean": td_error.abs().mean(), "q_mean": q_value.mean(),
                           "target_value_mean": target.mean()}
            if self.use_weights:
                diagnostics["weight_mean"] = weight.mean()
                diagnostics[WEIGHT_ESS] = effective_sample_size(weight)
        return loss, diagnostics

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """``"loss_value"`` and the diagnostics; writes δ² into ``tensordict["td_error"]``."""
        loss, diagnostics = self.value_loss(tensordict)
        tensordict.set(self.tensor_keys.priority, diagnostics.pop("td_error").unsqueeze(-1))
        return TensorDict({"loss_value": loss, **diagnostics}, batch_size=[])
