"""Stage 2 of WBRM: the weighted Bellman residual loss, Section 3 of the paper."""
from __future__ import annotations

import math
import warnings
from contextlib import nullcontext
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import dispatch, TensorDictModule
from tensordict.utils import NestedKey
from torchrl.data import Bounded, Composite, TensorSpec
from torchrl.modules import QValueActor
from torchrl.objectives.common import LossModule
from torchrl.objectives.utils import dispatch_value_estimator, ValueEstimators
from torchrl.objectives.value import TD0Estimator, ValueEstimatorBase
from torchrl.objectives.value.functional import td0_return_estimate

from torchrl_wbrm.modules.maximisers import (
    ActionMaximiser,
    ActorMaximiser,
    GreedyDiscreteMaximiser,
    SampledActionMaximiser,
    uniform_actions,
)
from torchrl_wbrm.objectives._fast import FunctionalCall
from torchrl_wbrm.objectives._utils import (
    as_bool_flag,
    check_finite,
    check_input_dtype,
    check_input_width,
    check_not_empty,
    check_reduction,
    check_same_features,
    check_sign,
    fast_get,
    get_entry,
    input_width,
    per_sample,
    reduce_batch,
)

__all__ = ["RESIDUALS", "WeightedBellmanLoss", "weighted_bellman_residual"]

RESIDUALS = ("squared", "absolute_mean")


def _next(key: NestedKey) -> tuple:
    """``key`` under ``"next"``, flattened: ``("next", "a", "b")`` rather than ``("next", ("a", "b"))``."""
    return ("next", *key) if isinstance(key, tuple) else ("next", key)


def weighted_bellman_residual(
    q_value: torch.Tensor,
    target_value: torch.Tensor,
    weight: torch.Tensor,
    *,
    residual: str = "squared",
    reduction: str = "mean",
) -> torch.Tensor:
    r"""The weighted Bellman residual of Section 3 ("Methodology").

    With ``δ_i = Q(X_i, A_i) − Y_i`` and ``Y_i = R_i + γ (1 − terminated_i) max_{a'} Q(X'_i, a')`` (the paper's
    ``Y_i := R_i + γ max_{A'} Q(X'_i, A')``, with no bootstrap after a termination):

    - ``"absolute_mean"`` (the paper's empirical loss): ``L̂_ŵ(Q) = | (1/n) Σ_i ŵ(X_i, A_i) δ_i |``. Note this is one
      equation per batch: on its own it pins Q only up to directions orthogonal to ŵ. On LQR exp1 (recipe budget,
      3 seeds, with the residual-gradient bootstrap) its Q̂ error was 4.7× the spread of Q* against 0.38× for
      ``"squared"``, and its greedy policy lost nearly the whole return (README, "Residual form and bootstrap mode").
    - ``"squared"``: ``(1/n) Σ_i ŵ(X_i, A_i) δ_i²`` (no ½ factor).

    Args:
        q_value (Tensor): ``Q(X_i, A_i)``, shape ``[*B]``.
        target_value (Tensor): ``Y_i``, shape ``[*B]``.
        weight (Tensor): ``ŵ(X_i, A_i) ≥ 0``, shape ``[*B]``.

    Keyword Args:
        residual (str): ``"squared"`` (default) or ``"absolute_mean"``.
        reduction (str): ``"mean"`` (default), ``"sum"`` or ``"none"``: per-sample ``ŵ_i δ_i²`` (squared), or the
            signed per-sample ``ŵ_i δ_i`` before the absolute value (absolute_mean).

    Examples:
        >>> import torch
        >>> q, y, w = torch.tensor([1.0, 2.0]), torch.tensor([0.0, 0.0]), torch.tensor([1.0, 0.5])
        >>> weighted_bellman_residual(q, y, w, residual="squared")  # (1·1 + 0.5·4) / 2
        tensor(1.5000)
        >>> weighted_bellman_residual(q, y, w, residual="absolute_mean")  # |(1·1 + 0.5·2) / 2|
        tensor(1.)
    """
    td_error = q_value - target_value
    if residual == "squared":
        return reduce_batch(weight * td_error.pow(2), reduction)
    if residual == "absolute_mean":
        weighted = reduce_batch(weight * td_error, reduction)
        return weighted if reduction == "none" else weighted.abs()
    raise ValueError(f"residual must be one of {RESIDUALS}, got {residual!r}.")


def _finite_and_non_negative(values: list[torch.Tensor], weight: torch.Tensor | None) -> bool:
    """Whether the floating CPU tensors of ``values`` and ``weight`` sum to a finite number and ``weight``'s minimum is
    finite and ``>= 0``, by one concatenated sum, one minimum and one host read (True where nothing is on the CPU:
    checks there would need a host sync; see :func:`check_sign`)."""
    values = [v for v in values if v.device.type == "cpu" and v.is_floating_point()]
    with_weight = weight is not None and weight.device.type == "cpu"
    if with_weight:
        values.append(weight)
    if not values:
        return True
    with torch.no_grad():
        if any(v.dtype != values[0].dtype for v in values):
            values = [v.to(torch.float64) for v in values]
        total = torch.cat([v.reshape(-1) for v in values]).sum()
        if not with_weight:
            return math.isfinite(total.item())
        total, low = torch.stack([total, values[-1].amin()]).tolist()
    return math.isfinite(total) and low >= 0  # (a NaN minimum fails the comparison)


class WeightedBellmanLoss(LossModule):
    r"""The ŵ-weighted Bellman residual for ``Q ≈ Q*`` (Section 3, "Methodology"; equation in
    :func:`weighted_bellman_residual`).

    ``δ_i = Q(x_i, a_i) − r_i − γ (1 − terminated_i) · max_{a'} Q(x'_i, a')``;
    ``residual="squared"``: ``mean_i ŵ_i δ_i²``; ``residual="absolute_mean"``: ``| mean_i ŵ_i δ_i |`` (the paper).
    ŵ is the density ratio dP^{π^e}/dP^{π^b} fitted by
    :class:`~torchrl_wbrm.objectives.RobustDensityRatioLoss`, read per sample from ``"density_ratio"``.

    The max over next actions (:mod:`torchrl_wbrm.modules.maximisers`):

    - discrete actions (``value_network`` a :class:`~torchrl.modules.QValueActor` or any module writing
      ``"action_value"``): the max over the Q head, as TorchRL's DQNLoss;
    - continuous actions with an ``actor_network`` μ: ``Q(x', μ(x'))`` (DDPG / TD3+BC), and a second loss
      ``"loss_actor" = −mean_i Q(x_i, μ(x_i))`` (optionally ŵ-weighted, optionally with TD3+BC's behaviour-cloning
      term);
    - continuous actions with ``maximiser="sampled"``: the best of uniform samples in ``action_spec`` (plus μ(x')
      when an actor exists); no actor needed.

    Bootstrapping: ``delay_value=True`` evaluates the max with a frozen copy of Q (target parameters, no gradient;
    update them with :class:`~torchrl.objectives.SoftUpdate` / :class:`~torchrl.objectives.HardUpdate`).
    ``delay_value=False`` is residual-gradient minimisation: the gradient flows through both ``Q(x, a)`` and
    ``max Q(x', ·)``. Truncation (``done`` without ``terminated``) bootstraps; termination does not.

    γ is set with ``make_value_estimator(gamma=...)`` (:class:`~torchrl.objectives.value.TD0Estimator`, the only
    supported estimator). Without that call TorchRL's default ``gamma = 0.99`` applies (the paper's LQR uses 0.9).

    Relation to TorchRL's :class:`~torchrl.objectives.DQNLoss`: ``distance_loss(..., "l2")`` is
    ``F.mse_loss(reduction="none")``, i.e. ``δ²`` with **no** ½ factor. With all weights 1 (or
    ``use_weights=False``), ``residual="squared"`` and ``delay_value=True``, ``"loss_value"`` therefore equals
    DQNLoss's ``"loss"`` with ``loss_function="l2"`` exactly (tested).

    Args:
        value_network (TensorDictModule): Q. Continuous actions: reads ``"observation"``, ``"action"`` (its
            in_keys) and writes ``"state_action_value"`` of shape ``[*B, 1]``. Discrete actions: reads the
            observation and writes ``"action_value"`` of shape ``[*B, n_actions]``; actions in the data are one-hot
            ``[*B, n]`` or indices ``[*B]`` / ``[*B, 1]``.

    Keyword Args:
        actor_network (TensorDictModule, optional): a deterministic actor μ writing ``"action"`` (continuous only).
        residual (str): ``"squared"`` (default) or ``"absolute_mean"`` (the paper's form).
        delay_value (bool): frozen target Q (``True``, default) or residual gradient (``False``).
        delay_actor (bool, optional): target copy of the actor for μ(x'). Defaults to ``delay_value``.
        use_weights (bool): read ŵ from ``"density_ratio"`` (``True``, default; a missing entry is a KeyError) or
            use weight 1 for every sample (the unweighted baseline).
        use_prioritized_weights (bool or "auto"): TorchRL's convention (:class:`~torchrl.objectives.LossModule`):
            with ``"auto"`` (default) or ``True``, a ``"priority_weight"`` entry in the batch (a prioritized replay
            buffer's importance weights, or any per-sample weight stored there) multiplies each sample's term,
            on top of ŵ when both are present; ``False`` ignores it. Unlike TorchRL's losses, which reduce a
            weighted batch as ``Σ wᵢ lᵢ / Σ wᵢ``, the product stays inside this loss's own mean (``mean ŵᵢ pᵢ δᵢ²``).
        maximiser (str or ActionMaximiser, optional): ``"discrete"``, ``"actor"``, ``"sampled"`` or an instance.
            Defaults to ``"discrete"`` for a Q head, ``"actor"`` with an actor, ``"sampled"`` otherwise.
        action_spec (Bounded, optional): action box for ``"sampled"``; defaults to the actor's spec if it has one.
        num_action_samples (int): uniform candidates per state for ``"sampled"``. Defaults to ``64``.
        weight_actor_loss (bool): weight each sample's actor loss by ŵ. Defaults to ``False``.
        bc_alpha (float, optional): TD3+BC's α. If given, ``loss_actor = mean_i [−λ Q(x_i, μ(x_i)) +
            mean_j (μ(x_i)_j − a_ij)²]`` with ``λ = α / mean|Q(x, μ(x))|`` (detached), as TD3+BC (Fujimoto & Gu
            2021; α = 2.5 there). Defaults to ``None`` (no behaviour cloning).
        reward_bound (float, optional): max|r| over the data (e.g. ``data["next", "reward"].abs().max()``), for the
            divergence warning: Q past ``q_bound_margin · reward_bound / (1 − γ)`` (2 × by default) warns once and
            sets ``q_bound_exceeded``. Defaults to ``None``: the running max|r| over the batches seen, checked from
            the ``q_bound_min_batches``-th batch (100) on.
        reduction (str, optional): ``"mean"`` (default, also for ``None``), ``"sum"`` or ``"none"``. For
            ``"squared"``, ``"none"`` gives the per-sample ``ŵ_i δ_i²``. For ``"absolute_mean"`` it gives the signed
            per-sample ``ŵ_i δ_i`` *before* the absolute value (``|mean|`` of it is the ``"mean"`` loss), and
            ``"sum"`` gives ``|Σ_i ŵ_i δ_i|``.

    Output: ``"loss_value"``, ``"loss_actor"`` (with an actor) and detached diagnostics ``"td_error_mean"``,
    ``"td_error_abs_mean"``, ``"q_mean"`` (mean Q(x, a)), ``"target_value_mean"``, with weights ``"weight_mean"``
    and ``"weight_ess"`` (Kish (Σŵ)²/Σŵ²), with an actor ``"actor_q_mean"`` and, with ``bc_alpha``, ``"bc_loss"``.
    ``forward`` writes ``δ²`` (detached, shape ``[*B, 1]``) into the input under ``"td_error"`` as DQNLoss does;
    no other input entry is changed.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Bounded
        >>> from torchrl.objectives import SoftUpdate
        >>> from torchrl_wbrm.modules import make_deterministic_actor, make_q_network
        >>> from torchrl_wbrm.objectives import WeightedBellmanLoss
        >>> spec = Bounded(-1.0, 1.0, (1,))
        >>> q = make_q_network(2, 1, initial_bias=0.0, num_cells=(32,))
        >>> actor = make_deterministic_actor(2, spec, num_cells=(32,))
        >>> loss = WeightedBellmanLoss(q, actor_network=actor, residual="squared")
        >>> loss.make_value_estimator(gamma=0.9)
        >>> updater = SoftUpdate(loss, tau=0.005)
        >>> n = 16
        >>> data = TensorDict({
        ...     "observation": torch.randn(n, 2),
        ...     "action": spec.rand((n,)),
        ...     "density_ratio": torch.rand(n, 1) * 2,
        ...     ("next", "observation"): torch.randn(n, 2),
        ...     ("next", "reward"): torch.randn(n, 1),
        ...     ("next", "done"): torch.zeros(n, 1, dtype=torch.bool),
        ...     ("next", "terminated"): torch.zeros(n, 1, dtype=torch.bool),
        ... }, [n])
        >>> out = loss(data)
        >>> sorted(k for k in out.keys() if k.startswith("loss_"))
        ['loss_actor', 'loss_value']
        >>> (out["loss_value"] + out["loss_actor"]).backward()
        >>> updater.step()
        >>> data["td_error"].shape
        torch.Size([16, 1])
    """

    @dataclass
    class _AcceptedKeys:
        """Maintains default values for all configurable tensordict keys.

        This class defines which tensordict keys can be set using '.set_keys(key_name=key_value)' and their
        default values.

        Attributes:
            action (NestedKey): The input tensordict key where the action is expected (and where the actor writes
                μ(x)). Defaults to ``"action"``.
            state_action_value (NestedKey): Where a continuous-action Q network writes Q(x, a).
                Defaults to ``"state_action_value"``.
            action_value (NestedKey): Where a discrete Q head writes the per-action values.
                Defaults to ``"action_value"``.
            weight (NestedKey): The input key of the per-sample weight ŵ(x, a). Defaults to ``"density_ratio"``.
            priority_weight (NestedKey): The input key of TorchRL's per-sample (importance) weight, multiplied with
                ŵ when present (see ``use_prioritized_weights``). Defaults to ``"priority_weight"``.
            priority (NestedKey): The input tensordict key where δ² is written back. Defaults to ``"td_error"``.
            reward (NestedKey): The reward key, read under ``"next"``. Defaults to ``"reward"``.
            done (NestedKey): The done key, read under ``"next"``. Defaults to ``"done"``.
            terminated (NestedKey): The terminated key, read under ``"next"``; no bootstrap where it is True.
                Defaults to ``"terminated"``.
        """

        action: NestedKey = "action"
        state_action_value: NestedKey = "state_action_value"
        action_value: NestedKey = "action_value"
        weight: NestedKey = "density_ratio"
        priority_weight: NestedKey = "priority_weight"
        priority: NestedKey = "td_error"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    default_value_estimator = ValueEstimators.TD0
    SUPPORTED_VALUE_ESTIMATORS = (ValueEstimators.TD0,)
    #: Call plain networks on tensors (:mod:`torchrl_wbrm.objectives._fast`) instead of through TensorDicts and
    #: ``to_module``; the same computation (tested). Set ``False`` on an instance to force the TensorDict path.
    fast_path: bool = True
    #: Q(x, a) past ``q_bound_margin · max|r| / (1 − γ)`` warns once: no discounted return of such rewards is that
    #: large, so Q is diverging. ``q_bound_exceeded`` then stays ``True``. max|r| is ``reward_bound`` when set (e.g.
    #: max|r| over the whole dataset: the trainer's and a script's best choice), else the running max over the
    #: batches seen, and then only after ``q_bound_min_batches`` batches (a rare large reward, as MountainCar's goal
    #: reward, is missing from most batches).
    q_bound_margin: float = 2.0
    q_bound_min_batches: int = 100
    q_bound_exceeded: bool = False

    value_network: TensorDictModule
    value_network_params: TensorDictParams
    target_value_network_params: TensorDictParams
    actor_network: TensorDictModule
    actor_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams

    def __init__(
        self,
        value_network: TensorDictModule,
        *,
        actor_network: TensorDictModule | None = None,
        residual: str = "squared",
        delay_value: bool = True,
        delay_actor: bool | None = None,
        use_weights: bool = True,
        use_prioritized_weights: str | bool = "auto",
        maximiser: str | ActionMaximiser | None = None,
        action_spec: TensorSpec | None = None,
        num_action_samples: int = 64,
        weight_actor_loss: bool = False,
        bc_alpha: float | None = None,
        reward_bound: float | None = None,
        reduction: str | None = None,
    ) -> None:
        reduction = check_reduction(reduction)
        if reward_bound is not None and not (math.isfinite(float(reward_bound)) and float(reward_bound) > 0):
            raise ValueError(f"reward_bound must be a finite number > 0 (max|r| over the data) or None, got "
                             f"{reward_bound!r}.")
        if residual not in RESIDUALS:
            raise ValueError(f"residual must be one of {RESIDUALS}, got {residual!r}.")
        discrete = isinstance(value_network, QValueActor) or self.default_keys.action_value in getattr(
            value_network, "out_keys", ()
        )
        if actor_network is None and (weight_actor_loss or bc_alpha is not None):
            raise ValueError("weight_actor_loss and bc_alpha configure the actor loss; pass an actor_network.")
        if bc_alpha is not None and not bc_alpha > 0:
            raise ValueError(f"bc_alpha must be > 0 or None, got {bc_alpha!r}.")
        if use_prioritized_weights not in (True, False, "auto"):
            raise ValueError(f"use_prioritized_weights must be True, False or 'auto', got {use_prioritized_weights!r}.")
        self._in_keys = None
        self._out_keys = None
        super().__init__()
        self.maximiser = self._make_maximiser(maximiser, discrete, actor_network, action_spec, num_action_samples)
        self.discrete = discrete
        self.residual = residual
        self.delay_value = bool(delay_value)
        self.delay_actor = self.delay_value if delay_actor is None else bool(delay_actor)
        self.use_weights = bool(use_weights)
        self.use_prioritized_weights = use_prioritized_weights
        self.weight_actor_loss = bool(weight_actor_loss)
        self.bc_alpha = None if bc_alpha is None else float(bc_alpha)
        self.reduction = reduction
        self.reward_bound = None if reward_bound is None else float(reward_bound)
        self.convert_to_functional(value_network, "value_network", create_target_params=self.delay_value)
        self.has_actor = actor_network is not None
        if self.has_actor:
            self.convert_to_functional(actor_network, "actor_network", create_target_params=self.delay_actor)

    @staticmethod
    def _make_maximiser(maximiser, discrete, actor_network, action_spec, num_action_samples) -> ActionMaximiser:
        if isinstance(maximiser, ActionMaximiser):
            return maximiser
        if discrete:
            if actor_network is not None:
                raise ValueError("A discrete Q head (writing 'action_value') takes no actor_network.")
            if maximiser not in (None, "discrete"):
                raise ValueError(f"A discrete Q head needs maximiser='discrete' (or None), got {maximiser!r}.")
            return GreedyDiscreteMaximiser()
        if maximiser is None:
            maximiser = "actor" if actor_network is not None else "sampled"
        if maximiser == "actor":
            if actor_network is None:
                raise ValueError("maximiser='actor' needs an actor_network.")
            return ActorMaximiser()
        if maximiser == "sampled":
            if action_spec is None:
                action_spec = getattr(actor_network, "spec", None)
            if isinstance(action_spec, Composite):
                action_spec = action_spec.get(WeightedBellmanLoss.default_keys.action, None)
            if not isinstance(action_spec, Bounded):
                raise ValueError(
                    "maximiser='sampled' needs a Bounded action_spec (or an actor whose spec is Bounded), "
                    f"got {type(action_spec).__name__}."
                )
            return SampledActionMaximiser(action_spec, num_samples=num_action_samples)
        raise ValueError(
            f"maximiser must be 'discrete', 'actor', 'sampled' or an ActionMaximiser, got {maximiser!r}."
        )

    # ---------------------------------------------------------------- keys and value estimator
    def _forward_value_estimator_keys(self, **kwargs) -> None:
        if self._value_estimator is not None:
            self._value_estimator.set_keys(
                value=self.tensor_keys.state_action_value,
                reward=self.tensor_keys.reward,
                done=self.tensor_keys.done,
                terminated=self.tensor_keys.terminated,
            )
        self._in_keys = None

    def make_value_estimator(self, value_type: ValueEstimators | None = None, **hyperparams) -> None:
        """Builds the TD(0) target ``r + γ (1 − terminated) · next_value``; set γ here (default 0.99).

        ``gamma`` must be a finite number in ``[0, 1]`` (a NaN or a γ above 1 is refused, naming it)."""
        if "gamma" in hyperparams:
            gamma = hyperparams["gamma"]
            try:
                value = float(gamma)
            except (TypeError, ValueError):
                raise ValueError(f"gamma must be a number in [0, 1], got {gamma!r}.") from None
            if not (math.isfinite(value) and 0.0 <= value <= 1.0):
                raise ValueError(f"gamma must be a finite number in [0, 1] (the discount), got {gamma!r}.")
        if value_type is None:
            value_type = self.default_value_estimator
        if isinstance(value_type, ValueEstimatorBase) or (
            isinstance(value_type, type) and issubclass(value_type, ValueEstimatorBase)
        ):
            return LossModule.make_value_estimator(self, value_type, **hyperparams)
        dispatch_value_estimator(
            self,
            value_type,
            supported=self.SUPPORTED_VALUE_ESTIMATORS,
            tensor_keys={
                "value": self.tensor_keys.state_action_value,
                "reward": self.tensor_keys.reward,
                "done": self.tensor_keys.done,
                "terminated": self.tensor_keys.terminated,
            },
            value_network=None,
            **hyperparams,
        )

    @property
    def _observation_keys(self) -> list[NestedKey]:
        """The value network's inputs other than the action (the state part of (x, a))."""
        return [key for key in self.value_network.in_keys if key != self.tensor_keys.action]

    @property
    def in_keys(self) -> list[NestedKey]:
        if self._in_keys is None:
            keys = [
                self.tensor_keys.action,
                _next(self.tensor_keys.reward),
                _next(self.tensor_keys.done),
                _next(self.tensor_keys.terminated),
                *self.value_network.in_keys,
                *[_next(key) for key in self._observation_keys],
            ]
            if self.has_actor:
                keys += [*self.actor_network.in_keys, *[_next(key) for key in self.actor_network.in_keys]]
            if self.use_weights:
                keys.append(self.tensor_keys.weight)
            self._in_keys = list(dict.fromkeys(keys))
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values):
        self._in_keys = values

    @property
    def out_keys(self) -> list[str]:
        if self._out_keys is None:
            keys = ["loss_value", "td_error_mean", "td_error_abs_mean", "q_mean", "target_value_mean"]
            if self.use_weights:
                keys += ["weight_mean", "weight_ess"]
            if self.has_actor:
                keys += ["loss_actor", "actor_q_mean"]
                if self.bc_alpha is not None:
                    keys.append("bc_loss")
            self._out_keys = keys
        return self._out_keys

    @out_keys.setter
    def out_keys(self, values):
        self._out_keys = values

    # ---------------------------------------------------------------- pieces
    def _network_facts(self) -> tuple[int | None, torch.dtype | None]:
        """``(input width, parameter dtype)`` of the value network (cached per network): what the batch's inputs must
        add up to and be cast to."""
        cache = self.__dict__.get("_facts_cache")
        if cache is None or cache[0] is not self.value_network:
            floats = [p for p in self.value_network_params.values(True, True) if p.is_floating_point()]
            cache = (self.value_network, input_width(self.value_network), floats[0].dtype if floats else None)
            self.__dict__["_facts_cache"] = cache
        return cache[1], cache[2]

    def _fast(self) -> tuple[FunctionalCall, FunctionalCall | None] | None:
        """``(Q call, actor call)`` for the tensor path, or ``None`` where the TensorDict path is needed (a discrete
        head, a custom maximiser, a network that is not a plain TensorDictModule, other output keys)."""
        actor = self.actor_network if self.has_actor else None
        cache = self.__dict__.get("_fast_cache")
        if cache is not None and cache[0] is self.value_network and cache[1] is actor and cache[3] == self.fast_path:
            return cache[2]
        plan = None
        if (
            self.fast_path
            and not self.discrete
            and type(self.maximiser) in (ActorMaximiser, SampledActionMaximiser)
            and list(self.value_network.out_keys) == [self.tensor_keys.state_action_value]
            and (actor is None or list(actor.out_keys) == [self.tensor_keys.action])
        ):
            value_call = FunctionalCall.build(self.value_network, self.value_network_params)
            actor_call = None if actor is None else FunctionalCall.build(actor, self.actor_network_params)
            if value_call is not None and (actor is None or actor_call is not None):
                plan = (value_call, actor_call)
        self.__dict__["_fast_cache"] = (self.value_network, actor, plan, self.fast_path)
        return plan

    def _td0_target(self, tensordict: TensorDictBase, next_value: torch.Tensor) -> torch.Tensor:
        """``r + γ (1 − terminated) · next_value`` as the TD(0) estimator computes it (its keys, its γ), without the
        TensorDict copy; other estimators (or options) go through ``value_estimate``."""
        estimator = self.value_estimator
        keys = getattr(estimator, "tensor_keys", None)
        if (
            not self.fast_path
            or type(estimator) is not TD0Estimator
            or getattr(estimator, "average_rewards", True)
            or fast_get(tensordict, keys.steps_to_next_obs) is not None
        ):
            reward = tensordict.get(_next(self.tensor_keys.reward))
            return estimator.value_estimate(tensordict.copy(), next_value=next_value.reshape(reward.shape))
        reward = fast_get(tensordict, _next(keys.reward))
        if estimator.gamma.device != reward.device:
            estimator.gamma = estimator.gamma.to(reward.device)
        done = fast_get(tensordict, _next(keys.done))
        terminated = fast_get(tensordict, _next(keys.terminated), done)
        return td0_return_estimate(
            gamma=estimator.gamma, next_state_value=next_value.reshape(reward.shape), reward=reward,
            terminated=terminated,
        )

    def _inputs(self, tensordict: TensorDictBase, keys, why: str) -> TensorDict:
        """A new TensorDict holding ``keys`` of ``tensordict`` (so the input is never written to)."""
        return TensorDict(
            {key: get_entry(tensordict, key, why) for key in keys},
            batch_size=tensordict.batch_size,
            device=tensordict.device,
        )

    def _weight(self, tensordict: TensorDictBase, check: bool = True) -> torch.Tensor:
        """The per-sample weight, shape ``[*B]`` (detached: the weights are fixed in stage 2): ŵ (``use_weights``)
        times the ``"priority_weight"`` entry where TorchRL's convention reads it, or ones when neither applies.

        ``check=False`` leaves ŵ's sign check to the caller (:meth:`bellman_error` with ``weight_to_check``)."""
        weight = None
        if self.use_weights:
            key = self.tensor_keys.weight
            weight = get_entry(
                tensordict, key, "the per-sample weight ŵ(x, a): write the ratio network's output there, or build "
                "the loss with use_weights=False"
            )
            weight = per_sample(weight, tensordict.batch_size, key).detach()
            if not weight.is_floating_point():  # integer (or bool) weights: counts, 0/1 selections
                weight = weight.to(self._network_facts()[1] or torch.get_default_dtype())
            if check:
                check_sign(weight, key, strictly_positive=False)
        priority_key = self.tensor_keys.priority_weight
        if self.use_prioritized_weights in (True, "auto") and not (self.use_weights and priority_key == self.tensor_keys.weight):
            priority = fast_get(tensordict, priority_key)
            if priority is not None:
                priority = per_sample(priority, tensordict.batch_size, priority_key).detach()
                if not priority.is_floating_point():
                    priority = priority.to(self._network_facts()[1] or torch.get_default_dtype())
                check_sign(priority, priority_key, strictly_positive=False)
                weight = priority if weight is None else weight * priority
        if weight is None:
            reward = get_entry(tensordict, _next(self.tensor_keys.reward), "the reward")
            return torch.ones(tensordict.batch_size, device=reward.device, dtype=reward.dtype)
        return weight

    def _chosen_q(self, tensordict: TensorDictBase) -> torch.Tensor:
        """Q(x, a) at the data's actions, shape ``[*B]``, with the online parameters (differentiable)."""
        fast = self._fast()
        if fast is not None:
            tensors = [get_entry(tensordict, key, "an input of the value network") for key in self.value_network.in_keys]
            key = self.tensor_keys.state_action_value
            return per_sample(fast[0](self.value_network_params, *tensors), tensordict.batch_size, key)
        keys = self._observation_keys if self.discrete else self.value_network.in_keys
        inputs = self._inputs(tensordict, keys, "an input of the value network")
        with self.value_network_params.to_module(self.value_network, preserve_module_state=False):
            outputs = self.value_network(inputs)
        if not self.discrete:
            key = self.tensor_keys.state_action_value
            return per_sample(get_entry(outputs, key, "the value network's output"), tensordict.batch_size, key)
        action_value = get_entry(outputs, self.tensor_keys.action_value, "the Q head's output")
        action = get_entry(tensordict, self.tensor_keys.action, "the action taken in the data")
        batch, num_actions = tensordict.batch_size, action_value.shape[-1]
        if action.shape == (*batch, num_actions):  # one-hot
            return (action_value * action.to(action_value.dtype)).sum(-1)
        if action.shape in (batch, (*batch, 1)) and not action.is_floating_point():  # indices
            if action.device.type == "cpu" and action.numel():
                low, high = (int(v) for v in torch.aminmax(action.long()))
                if low < 0 or high >= num_actions:
                    raise ValueError(
                        f"Entry {self.tensor_keys.action!r} holds action indices from {low} to {high}; the Q head has "
                        f"{num_actions} actions, so indices must lie in [0, {num_actions - 1}]."
                    )
            return action_value.gather(-1, action.reshape(*batch, 1).long()).squeeze(-1)
        raise ValueError(
            f"Entry {self.tensor_keys.action!r} has shape {tuple(action.shape)} and dtype {action.dtype}; a Q head "
            f"over {num_actions} actions expects one-hot actions {(*batch, num_actions)} or integer indices "
            f"{tuple(batch)} / {(*batch, 1)}."
        )

    def _actor_action(self, inputs: TensorDictBase, params: TensorDictBase) -> torch.Tensor:
        """μ(x) with the given actor parameters."""
        actor_inputs = self._inputs(inputs, self.actor_network.in_keys, "an input of the actor")
        with params.to_module(self.actor_network, preserve_module_state=False):
            return self.actor_network(actor_inputs).get(self.tensor_keys.action)

    def next_state_value(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``max_{a'} Q(x', a')``, shape ``[*B]``: target Q under no_grad (``delay_value``) or online Q with grad."""
        next_td = get_entry(tensordict, "next", "the sub-TensorDict of next states")
        fast = self._fast()
        if fast is not None:
            return self._fast_next_state_value(next_td, fast)
        next_inputs = self._inputs(next_td, self._observation_keys, "a next-state input of the value network")
        actor_action = None
        if self.has_actor:
            with torch.no_grad():  # the value loss never trains the actor
                actor_action = self._actor_action(next_td, self.target_actor_network_params)
        params = self.target_value_network_params if self.delay_value else self.value_network_params
        with torch.no_grad() if self.delay_value else nullcontext():
            with params.to_module(self.value_network, preserve_module_state=False):
                return self.maximiser(
                    self.value_network,
                    next_inputs,
                    action_key=self.tensor_keys.action,
                    value_key=self.tensor_keys.action_value if self.discrete else self.tensor_keys.state_action_value,
                    actor_action=actor_action,
                )

    def _fast_next_state_value(self, next_td: TensorDictBase, fast) -> torch.Tensor:
        """:meth:`next_state_value` on tensors: the same candidates (μ'(x'), or the uniform draws then μ'(x')), the
        same ``[K, *B]`` evaluation of Q and the max over K."""
        value_call, actor_call = fast
        action_key = self.tensor_keys.action
        batch = next_td.batch_size
        next_inputs = {key: get_entry(next_td, key, "a next-state input of the value network")
                       for key in self._observation_keys}
        actor_action = None
        if actor_call is not None:
            with torch.no_grad():  # the value loss never trains the actor
                actor_in = [get_entry(next_td, key, "an input of the actor") for key in self.actor_network.in_keys]
                actor_action = actor_call(self.target_actor_network_params, *actor_in)
        params = self.target_value_network_params if self.delay_value else self.value_network_params
        with torch.no_grad() if self.delay_value else nullcontext():
            if isinstance(self.maximiser, SampledActionMaximiser):
                m = self.maximiser
                candidates = uniform_actions(m.low, m.high, m.num_samples, batch)
                if actor_action is not None:
                    candidates = torch.cat([candidates, actor_action.unsqueeze(0)], 0)
            else:
                if actor_action is None:
                    raise ValueError("ActorMaximiser needs actor_action = μ(x); build the loss with an actor_network.")
                # one candidate: Q(x', μ'(x')) itself (the [1, *B] evaluation and its max over one are the same
                # matrix products on the same rows, and the max of one value is that value)
                tensors = [actor_action if key == action_key else next_inputs[key] for key in self.value_network.in_keys]
                return value_call(params, *tensors).squeeze(-1)
            k = candidates.shape[0]
            tensors = []
            for key in self.value_network.in_keys:
                if key == action_key:
                    tensors.append(candidates)
                else:
                    tensors.append(next_inputs[key].expand(k, *next_inputs[key].shape))
            values = value_call(params, *tensors).squeeze(-1)  # [K, *B]
            return values.max(0).values

    # ---------------------------------------------------------------- input checks
    def _checked_inputs(self, tensordict: TensorDictBase, weight_to_check: torch.Tensor | None = None) -> TensorDictBase:
        """Check a batch against the documented shapes before any network sees it; return it with bool flags.

        A ValueError names the key and both shapes for a reward or flag that is not one value per sample, or an
        observation whose next-state counterpart has another shape, and every input key with its width when the
        widths do not add up to the value network's input features; an empty batch and NaN/inf in the reward,
        observations or action (CPU tensors) are ValueErrors too; an input whose dtype is not the network's is a
        TypeError naming both. ``done``/``terminated`` of any integer dtype holding 0/1 are read as bools, and flags
        of shape ``[*B]`` beside a reward ``[*B, 1]`` (or the reverse) take the reward's shape (a shallow copy; the
        input is not modified); a float flag is a TypeError.
        ``weight_to_check`` (ŵ, ``[*B]``) is checked finite and non-negative first (:func:`check_sign`'s error).

        The finite checks (and ŵ's sign) are one sum over all the entries and one minimum, read in one host sync: a
        sum is finite iff every entry is, unless it overflows, and only then (or on a failure) is each entry checked
        on its own, in the order above, for the error that names it.
        """
        batch = tensordict.batch_size
        check_not_empty(batch, "Bellman-residual")
        flags = {}
        checks: list[tuple[torch.Tensor, NestedKey]] = []
        reward_shape = None
        for key, why in ((self.tensor_keys.reward, "the reward"), (self.tensor_keys.done, "episode-end flag"),
                         (self.tensor_keys.terminated, "episode-end flag; no bootstrap where it is True")):
            value = per_sample(get_entry(tensordict, _next(key), why), batch, _next(key))
            if key == self.tensor_keys.reward:
                checks.append((value, _next(key)))
                reward_shape = fast_get(tensordict, _next(key)).shape
            else:
                raw = fast_get(tensordict, _next(key))
                flag = as_bool_flag(raw, _next(key))
                if flag.shape != reward_shape:  # [B] and [B, 1] mixed: one value per sample either way
                    flag = flag.reshape(reward_shape)
                if flag is not raw:
                    flags[key] = flag
        next_td = get_entry(tensordict, "next", "the sub-TensorDict of next states")
        width, dtype = self._network_facts()
        inputs, next_inputs = {}, {}
        for key in self._observation_keys:
            obs = get_entry(tensordict, key, "an input of the value network")
            next_obs = get_entry(next_td, key, "a next-state input of the value network")
            check_same_features(obs, next_obs, key, _next(key), batch, batch)
            checks += [(obs, key), (next_obs, _next(key))]
            inputs[key], next_inputs[_next(key)] = obs, next_obs
        if not self.discrete:
            action = get_entry(tensordict, self.tensor_keys.action, "the action taken in the data")
            checks.append((action, self.tensor_keys.action))
            inputs[self.tensor_keys.action] = action
        check_input_dtype(dtype, {**inputs, **next_inputs}, "value network")
        check_input_width(width, inputs, batch, "value network")
        if not _finite_and_non_negative([v for v, _ in checks], weight_to_check):
            if weight_to_check is not None:
                check_sign(weight_to_check, self.tensor_keys.weight, strictly_positive=False)
            for value, key in checks:
                check_finite(value, key)
        if flags:  # a shallow copy with bool flags, so the caller's TensorDict is not modified
            tensordict = tensordict.copy()
            next_td = next_td.copy()
            for key, flag in flags.items():
                next_td.set(key, flag)
            tensordict.set("next", next_td)
        return tensordict

    # ---------------------------------------------------------------- losses
    def bellman_error(self, tensordict: TensorDictBase, weight_to_check: torch.Tensor | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(Q(x_i, a_i), Y_i)``, each of shape ``[*B]``, with ``Y_i = r_i + γ (1 − terminated_i) max Q(x'_i, ·)``.

        ``Y`` carries a gradient exactly when the bootstrap is by residual gradient (``delay_value=False``).
        Shared by :meth:`value_loss` and by subclasses (:class:`~torchrl_wbrm.objectives.MABOLoss`).
        ``weight_to_check``: ŵ, checked with the batch's entries (see :meth:`_checked_inputs`).
        """
        tensordict = self._checked_inputs(tensordict, weight_to_check)
        q_value = self._chosen_q(tensordict)
        next_value = self.next_state_value(tensordict)
        target_value = self._td0_target(tensordict, next_value)
        return q_value, per_sample(target_value, tensordict.batch_size, _next(self.tensor_keys.reward))

    def value_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The weighted Bellman residual (:func:`weighted_bellman_residual`); returns ``(loss, diagnostics)``.

        The diagnostics include the detached per-sample ``"td_error"`` (δ²), which :meth:`forward` writes back.
        """
        weight = self._weight(tensordict, check=False)
        q_value, target_value = self.bellman_error(tensordict, weight if self.use_weights else None)
        if self.use_weights and weight.device.type == "cpu" and not bool(weight.any()):
            raise ValueError(
                f"Every weight of the batch is 0 (entry {self.tensor_keys.weight!r}"
                f"{', times ' + repr(self.tensor_keys.priority_weight) if self._reads_priority(tensordict) else ''}): "
                "the weighted residual would be 0 and its effective sample size undefined. Check the stored weights "
                "(a collapsed density ratio?) or sample larger batches."
            )
        self._watch_q_bound(q_value, tensordict)
        loss = weighted_bellman_residual(
            q_value,
            target_value,
            weight,
            residual=self.residual,
            reduction=self.reduction,
        )
        with torch.no_grad():
            td_error = q_value - target_value
            diagnostics = {
                "td_error": td_error.pow(2),
                "td_error_mean": td_error.mean(),
                "td_error_abs_mean": td_error.abs().mean(),
                "q_mean": q_value.mean(),
                "target_value_mean": target_value.mean(),
            }
            if self.use_weights:
                diagnostics["weight_mean"] = weight.mean()
                diagnostics["weight_ess"] = weight.sum().pow(2) / weight.pow(2).sum()
        return loss, diagnostics

    def _reads_priority(self, tensordict: TensorDictBase) -> bool:
        key = self.tensor_keys.priority_weight
        return (self.use_prioritized_weights in (True, "auto") and not (self.use_weights and key == self.tensor_keys.weight)
                and fast_get(tensordict, key) is not None)

    @torch.no_grad()
    def _watch_q_bound(self, q_value: torch.Tensor, tensordict: TensorDictBase) -> None:
        """Warn once when ``max |Q(x, a)|`` passes ``q_bound_margin · max|r| / (1 − γ)``: no discounted return of
        these rewards is that large. max|r| is :attr:`reward_bound`, or the running max over every batch seen (kept
        on the device, no host sync), and then no warning before ``q_bound_min_batches`` batches. Checked on every
        call for CPU tensors and every 100th call elsewhere (a check reads two numbers back from the device)."""
        if self.q_bound_exceeded:
            return
        calls = self.__dict__.get("_q_bound_calls", 0) + 1
        self.__dict__["_q_bound_calls"] = calls
        bound_given = getattr(self, "reward_bound", None)
        if bound_given is None:
            reward = fast_get(tensordict, _next(self.tensor_keys.reward))
            peak = reward.detach().abs().amax().to(torch.float64)
            seen = self.__dict__.get("_max_abs_reward")
            self.__dict__["_max_abs_reward"] = peak if seen is None else torch.maximum(seen.to(peak.device), peak)
            if calls < self.q_bound_min_batches:
                return
        if q_value.device.type != "cpu" and calls % 100:
            return
        gamma = float(self.value_estimator.gamma)
        if not gamma < 1.0:
            return
        if bound_given is None:
            q_max, r_max = torch.stack([q_value.abs().amax().to(torch.float64), self.__dict__["_max_abs_reward"]]).tolist()
            source = f"over the {calls} batches seen"
        else:
            q_max, r_max = float(q_value.abs().amax()), float(bound_given)
            source = "the reward_bound given"
        bound = self.q_bound_margin * r_max / (1.0 - gamma)
        if r_max > 0 and q_max > bound:
            self.q_bound_exceeded = True
            warnings.warn(
                f"WeightedBellmanLoss: |Q(x, a)| reached {q_max:.4g}, past {self.q_bound_margin:g} · max|r| / (1 − γ) "
                f"= {bound:.4g} (max|r| = {r_max:.4g}, {source}; γ = {gamma:g}), larger than any discounted return "
                "of these rewards: Q is diverging. Likely cause: Q started far from its targets (set make_q_network's "
                "initial_bias to mean(r) / (1 − γ), e.g. initial_q_value(data, gamma)); else a learning rate too high "
                "for the bootstrap, or a target updated too fast (delay_value=True with a smaller SoftUpdate tau). "
                "This warning is given once per loss.",
                UserWarning,
                stacklevel=3,
            )

    def actor_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """``−mean_i Q(x_i, μ(x_i))`` (Q frozen), optionally ŵ-weighted and with TD3+BC's cloning term.

        Only the actor receives gradients. Returns ``(loss, diagnostics)``.
        """
        if not self.has_actor:
            raise ValueError("actor_loss needs an actor_network; this loss was built without one.")
        key = self.tensor_keys.state_action_value
        fast = self._fast()
        if fast is not None:
            value_call, actor_call = fast
            actor_in = [get_entry(tensordict, k, "an input of the actor") for k in self.actor_network.in_keys]
            mu = actor_call(self.actor_network_params, *actor_in)
            q_in = [mu if k == self.tensor_keys.action else get_entry(tensordict, k, "an input of the value network")
                    for k in self.value_network.in_keys]
            q_actor = per_sample(value_call(self.value_network_params, *q_in, detach=True), tensordict.batch_size, key)
        else:
            mu = self._actor_action(tensordict, self.actor_network_params)
            q_inputs = self._inputs(tensordict, self._observation_keys, "an input of the value network")
            q_inputs.set(self.tensor_keys.action, mu)
            with self.value_network_params.detach().to_module(self.value_network, preserve_module_state=False):
                q_outputs = self.value_network(q_inputs)
            q_actor = per_sample(get_entry(q_outputs, key, "the value network's output"), tensordict.batch_size, key)
        per_sample_loss = -q_actor
        diagnostics = {"actor_q_mean": q_actor.detach().mean()}
        if self.bc_alpha is not None:
            action = get_entry(tensordict, self.tensor_keys.action, "the dataset action for behaviour cloning")
            if action.shape != mu.shape:
                raise ValueError(
                    f"Entry {self.tensor_keys.action!r} has shape {tuple(action.shape)} but the actor writes "
                    f"{tuple(mu.shape)}."
                )
            bc = (mu - action).pow(2).reshape(*tensordict.batch_size, -1).mean(-1)
            lmbd = self.bc_alpha / q_actor.abs().mean().detach().clamp_min(1e-6)
            per_sample_loss = lmbd * per_sample_loss + bc
            diagnostics["bc_loss"] = bc.detach().mean()
        if self.weight_actor_loss:
            per_sample_loss = per_sample_loss * self._weight(tensordict)
        return reduce_batch(per_sample_loss, self.reduction), diagnostics

    def _value_terms(self, tensordict: TensorDictBase) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """The losses of one forward other than the actor's (here ``"loss_value"``) and their diagnostics, from one
        evaluation of Q and its target; subclasses with more players (MABO's adversary) add theirs."""
        loss_value, diagnostics = self.value_loss(tensordict)
        return {"loss_value": loss_value}, diagnostics

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Computes ``"loss_value"`` (and ``"loss_actor"``) and writes δ² into ``tensordict["td_error"]``."""
        losses, diagnostics = self._value_terms(tensordict)
        td_error = diagnostics.pop("td_error")
        tensordict.set(self.tensor_keys.priority, td_error.unsqueeze(-1))
        out = {**losses, **diagnostics}
        if self.has_actor:
            loss_actor, actor_diagnostics = self.actor_loss(tensordict)
            out.update(loss_actor=loss_actor, **actor_diagnostics)
        return TensorDict(out, batch_size=[])
