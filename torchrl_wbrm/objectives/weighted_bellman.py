"""Stage 2 of WBRM: the weighted Bellman residual loss, Section 3 of the paper."""
from __future__ import annotations

import math
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

from torchrl_wbrm.keys import DENSITY_RATIO, PRIORITY_WEIGHT, WEIGHT_ESS
from torchrl_wbrm.modules.maximisers import (
    ActionMaximiser,
    ActorMaximiser,
    GreedyDiscreteMaximiser,
    SampledActionMaximiser,
)
from torchrl_wbrm.objectives._fast import NetworkCall, named_tensors
from torchrl_wbrm.objectives.functional import (
    RESIDUALS,
    bellman_residual,
    bellman_target,
    effective_sample_size,
    per_sample_weight,
    td3bc_lambda,
    weighted_bellman_residual,
)
from torchrl_wbrm.objectives._utils import (
    as_bool_flag,
    check_finite,
    check_input_dtype,
    check_input_width,
    check_not_empty,
    check_reduction,
    check_same_features,
    check_sign,
    checks_run,
    get_entry,
    input_width,
    per_sample,
)

#: How ŵ enters the reduction (``weight_reduction``): ``"mean"``, the paper's ``(1/n) Σ ŵᵢ lᵢ``, or
#: ``"normalised"``, the self-normalised ``Σ ŵᵢ lᵢ / Σ ŵᵢ`` of :class:`~torchrl_wbrm.objectives.WeightedLoss`.
WEIGHT_REDUCTIONS = ("mean", "normalised")

__all__ = ["RESIDUALS", "WEIGHT_REDUCTIONS", "WeightedBellmanLoss", "weighted_bellman_residual"]


def _next(key: NestedKey) -> tuple:
    """``key`` under ``"next"``, flattened: ``("next", "a", "b")`` rather than ``("next", ("a", "b"))``."""
    return ("next", *key) if isinstance(key, tuple) else ("next", key)


def _product(a: torch.Tensor | None, b: torch.Tensor | None) -> torch.Tensor | None:
    """``a · b``, or the one that is not ``None`` (``None`` if both are)."""
    if a is None or b is None:
        return a if b is None else b
    return a * b.to(a.dtype)


def _masked_mean(value: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """The mean over the rows where ``mask`` holds (all rows without one); ``value`` may lead with K critics."""
    if value.ndim > (mask.ndim if mask is not None else value.ndim):
        value = value.mean(0)
    if mask is None:
        return value.mean()
    return torch.where(mask, value, torch.zeros_like(value)).sum() / mask.sum().clamp_min(1)


def _bounded_action_spec(action_spec, actor_network) -> Bounded | None:
    """The Bounded action spec given, or the actor's (the ``"action"`` entry of a Composite); ``None`` if neither."""
    if action_spec is None:
        action_spec = getattr(actor_network, "spec", None)
    if isinstance(action_spec, Composite):
        action_spec = action_spec.get(WeightedBellmanLoss.default_keys.action, None)
    return action_spec if isinstance(action_spec, Bounded) else None


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
    :func:`~torchrl_wbrm.objectives.functional.weighted_bellman_residual`).

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

    Bootstrapping, with TorchRL's meanings: ``delay_value=True`` evaluates the max with a frozen copy of Q (target
    parameters, no gradient; update them with :class:`~torchrl.objectives.SoftUpdate` /
    :class:`~torchrl.objectives.HardUpdate`); ``delay_value=False`` with the online parameters, detached
    (semi-gradient, as ``DQNLoss(delay_value=False)``). ``residual_gradient=True`` (with ``delay_value=False``) is
    residual-gradient minimisation: the gradient flows through both ``Q(x, a)`` and ``max Q(x', ·)``. Truncation
    (``done`` without ``terminated``) bootstraps; termination does not.

    Reduction, with TorchRL's rule (:meth:`~torchrl.objectives.LossModule._reduce_loss`): rows where a validity mask
    (``("collector", "mask")`` or ``"shifted_valid"``, see ``loss_mask_key``) is False are dropped, and a
    ``"priority_weight"`` p reduces as ``Σ pᵢ lᵢ / Σ pᵢ``. ŵ enters each term, ``lᵢ = ŵᵢ δᵢ²``, so that the loss is
    the paper's ``(1/n) Σ ŵᵢ δᵢ²`` (``weight_reduction="mean"``, default): with ŵ normalised to mean 1 over the data
    (:func:`~torchrl_wbrm.ratio.store_density_ratio`), this is an unbiased estimate of the expert-weighted
    ``E_{π^e}[δ²]``, and its step size does not depend on the batch's own mean of ŵ.
    ``weight_reduction="normalised"`` moves ŵ into the reduction's weights, ``Σ ŵᵢ pᵢ δᵢ² / Σ ŵᵢ pᵢ``, the
    self-normalised estimate of :class:`~torchrl_wbrm.objectives.WeightedLoss` (its value on the same batch, tested):
    biased for small batches, with each batch's step rescaled by 1/mean(ŵ). The default is the paper's estimator,
    the one its analysis is about; ``python examples/wbrm_ddpg_lqr.py --weight-reduction normalised`` runs the
    other.

    Twin critics, as TD3: ``num_qvalue_nets=K`` keeps K critics (parameters stacked, TorchRL's
    ``convert_to_functional(..., expand_dim=K)``), bootstraps on the minimum over the K target critics, sums the K
    critics' terms, and trains the actor on the first critic. ``policy_noise=σ`` smooths the target action as TD3:
    ``μ'(x') + clamp(σ ε, −noise_clip, noise_clip)``, clamped to the action box (TorchRL's ``TD3Loss`` critic target
    on the same networks, tested).

    vmap and compile: ``forward`` and the public loss methods make no host read where
    ``torch.compiler.is_compiling()`` or a functorch transform (``torch.vmap``) is active; there the input checks of
    values (finite, signs, action indices) skip themselves, and ``check_inputs=False`` turns
    the value checks off in eager use too. ``vmap_randomness`` is ``"different"`` where the loss draws random
    numbers (``maximiser="sampled"``, ``policy_noise``). A dtype or device move (``.double()``, ``.to(device)``)
    clears every cache (all are ``_cache``-named, dropped by TorchRL's ``_erase_cache``).

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
        delay_value (bool): frozen target Q (``True``, default) or the online Q, detached (``False``).
        delay_actor (bool, optional): target copy of the actor for μ(x'). Defaults to ``delay_value``.
        residual_gradient (bool): differentiate through ``max Q(x', ·)`` too (residual-gradient minimisation; needs
            ``delay_value=False``). Defaults to ``False``.
        num_qvalue_nets (int): the number K of critics (TD3's twin critics: 2). Defaults to ``1``.
        policy_noise (float, optional): TD3's target policy smoothing σ for the actor maximiser. Defaults to ``None``
            (none; TD3 uses 0.2).
        noise_clip (float): TD3's clip of the smoothing noise. Defaults to ``0.5``.
        use_weights (bool): read ŵ from ``"density_ratio"`` (``True``, default; a missing entry is a KeyError) or
            use weight 1 for every sample (the unweighted baseline).
        use_prioritized_weights (bool or "auto"): TorchRL's convention (:class:`~torchrl.objectives.LossModule`):
            with ``"auto"`` (default) or ``True``, a ``"priority_weight"`` entry in the batch (a prioritized replay
            buffer's importance weights, or any per-sample weight stored there) multiplies each sample's term,
            reduced as TorchRL reduces it, ``Σ pᵢ lᵢ / Σ pᵢ`` (with ŵ: ``Σ pᵢ ŵᵢ δᵢ² / Σ pᵢ``); ``False`` ignores it.
        weight_reduction (str): ``"mean"`` (default: the paper's ``(1/n) Σ ŵᵢ lᵢ``) or ``"normalised"``
            (``Σ ŵᵢ lᵢ / Σ ŵᵢ``); see above.
        maximiser (str or ActionMaximiser, optional): ``"discrete"``, ``"actor"``, ``"sampled"`` or an instance.
            Defaults to ``"discrete"`` for a Q head, ``"actor"`` with an actor, ``"sampled"`` otherwise.
        action_spec (Bounded, optional): action box for ``"sampled"``; defaults to the actor's spec if it has one.
        num_action_samples (int): uniform candidates per state for ``"sampled"``. Defaults to ``64``.
        weight_actor_loss (bool): weight each sample's actor loss by ŵ. Defaults to ``False``.
        bc_alpha (float, optional): TD3+BC's α. If given, ``loss_actor = mean_i [−λ Q(x_i, μ(x_i)) +
            mean_j (μ(x_i)_j − a_ij)²]`` with ``λ = α / mean|Q(x, μ(x))|`` (detached), as TD3+BC (Fujimoto & Gu
            2021; α = 2.5 there). Defaults to ``None`` (no behaviour cloning).
        check_inputs (bool): check the batch's values (finite entries, non-negative ŵ, action indices in range) in
            eager use; each check is a host read. Defaults to ``True``; skipped under compile and vmap regardless.
        reduction (str, optional): ``"mean"`` (default, also for ``None``), ``"sum"`` or ``"none"``. For
            ``"squared"``, ``"none"`` gives the per-sample ``ŵ_i δ_i²``. For ``"absolute_mean"`` it gives the signed
            per-sample ``ŵ_i δ_i`` *before* the absolute value (``|mean|`` of it is the ``"mean"`` loss), and
            ``"sum"`` gives ``|Σ_i ŵ_i δ_i|``.

    Output: ``"loss_value"``, ``"loss_actor"`` (with an actor) and detached diagnostics ``"td_error_mean"``,
    ``"td_error_abs_mean"``, ``"q_mean"`` (mean Q(x, a)), ``"target_value_mean"``, with weights ``"weight_mean"``
    and ``"weight_ess"`` (Kish (Σŵ)²/Σŵ²), with an actor ``"actor_q_mean"`` and ``"actor_q_abs_mean"`` (the batch
    means of Q(x, μ(x)) and of its absolute value) and, with ``bc_alpha``, ``"bc_loss"``.
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
    #: How :class:`~torchrl_wbrm.objectives._fast.NetworkCall` calls a plain network: on tensors (``True``) or
    #: through a TensorDict and ``to_module`` (``False``); the same computation either way (tested).
    fast_path: bool = True

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
        residual_gradient: bool = False,
        num_qvalue_nets: int = 1,
        policy_noise: float | None = None,
        noise_clip: float = 0.5,
        use_weights: bool = True,
        weight_reduction: str = "mean",
        use_prioritized_weights: str | bool = "auto",
        maximiser: str | ActionMaximiser | None = None,
        action_spec: TensorSpec | None = None,
        num_action_samples: int = 64,
        weight_actor_loss: bool = False,
        bc_alpha: float | None = None,
        check_inputs: bool = True,
        reduction: str | None = None,
    ) -> None:
        reduction = check_reduction(reduction)
        if residual_gradient and delay_value:
            raise ValueError("residual_gradient=True differentiates through max Q(x', ·) of the online Q; it needs "
                             "delay_value=False (a frozen target has no gradient to give).")
        if not (isinstance(num_qvalue_nets, int) and num_qvalue_nets >= 1):
            raise ValueError(f"num_qvalue_nets must be an int >= 1, got {num_qvalue_nets!r}.")
        if num_qvalue_nets > 1 and residual != "squared":
            raise NotImplementedError(f"num_qvalue_nets={num_qvalue_nets} (twin critics) is implemented for "
                                      f"residual='squared' only, got residual={residual!r}.")
        if weight_reduction not in WEIGHT_REDUCTIONS:
            raise ValueError(f"weight_reduction must be one of {WEIGHT_REDUCTIONS}, got {weight_reduction!r}.")
        if policy_noise is not None:
            if actor_network is None:
                raise ValueError("policy_noise smooths the target actor's action μ'(x'); pass an actor_network.")
            if not (math.isfinite(float(policy_noise)) and float(policy_noise) >= 0):
                raise ValueError(f"policy_noise must be a finite number >= 0 or None, got {policy_noise!r}.")
            if not (math.isfinite(float(noise_clip)) and float(noise_clip) >= 0):
                raise ValueError(f"noise_clip must be a finite number >= 0, got {noise_clip!r}.")
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
        self.residual_gradient = bool(residual_gradient)
        self.num_qvalue_nets = int(num_qvalue_nets)
        self.policy_noise = None if policy_noise is None else float(policy_noise)
        self.noise_clip = float(noise_clip)
        self.weight_reduction = weight_reduction
        self.check_inputs = bool(check_inputs)
        self.use_weights = bool(use_weights)
        self.use_prioritized_weights = use_prioritized_weights
        self.weight_actor_loss = bool(weight_actor_loss)
        self.bc_alpha = None if bc_alpha is None else float(bc_alpha)
        self.reduction = reduction
        self.convert_to_functional(value_network, "value_network",
                                   expand_dim=self.num_qvalue_nets if self.num_qvalue_nets > 1 else None,
                                   create_target_params=self.delay_value)
        self.has_actor = actor_network is not None
        if self.has_actor:
            self.convert_to_functional(actor_network, "actor_network", create_target_params=self.delay_actor)
        if self.policy_noise is not None:
            spec = _bounded_action_spec(action_spec, actor_network)
            if spec is None:
                raise ValueError("policy_noise clamps μ'(x') + noise to the action box: pass a Bounded action_spec "
                                 "(or an actor whose spec is Bounded).")
            self.register_buffer("min_action", spec.space.low.clone())
            self.register_buffer("max_action", spec.space.high.clone())

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
            spec = _bounded_action_spec(action_spec, actor_network)
            if spec is None:
                raise ValueError(
                    "maximiser='sampled' needs a Bounded action_spec (or an actor whose spec is Bounded), "
                    f"got {type(action_spec if action_spec is not None else getattr(actor_network, 'spec', None)).__name__}."
                )
            return SampledActionMaximiser(spec, num_samples=num_action_samples)
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

        ``gamma`` must be a finite number in ``[0, 1]`` (a NaN or a γ above 1 is refused, naming it). The target is
        :func:`~torchrl_wbrm.objectives.functional.bellman_target` with the estimator's keys and γ, so only a
        :class:`~torchrl.objectives.value.TD0Estimator` without ``average_rewards`` is accepted."""
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
            LossModule.make_value_estimator(self, value_type, **hyperparams)
            return self._check_value_estimator()
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
        self._check_value_estimator()

    def _check_value_estimator(self) -> None:
        estimator = self._value_estimator
        if not isinstance(estimator, TD0Estimator) or getattr(estimator, "average_rewards", False):
            self._value_estimator = None
            raise ValueError(
                f"{type(self).__name__} computes the TD(0) target r + γ (1 − terminated) max Q(x', ·); got "
                f"{type(estimator).__name__}"
                f"{' with average_rewards=True' if isinstance(estimator, TD0Estimator) else ''}. Use "
                "make_value_estimator(gamma=...) (a TD0Estimator without average_rewards)."
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
            priority_key = getattr(self.tensor_keys, "priority_weight", None)  # (a subclass's keys may have none)
            if priority_key is not None and self.use_prioritized_weights in (True, "auto"):
                keys.append(priority_key)
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
                keys += ["weight_mean", WEIGHT_ESS]
            if self.has_actor:
                keys += ["loss_actor", "actor_q_mean", "actor_q_abs_mean"]
                if self.bc_alpha is not None:
                    keys.append("bc_loss")
            self._out_keys = keys
        return self._out_keys

    @out_keys.setter
    def out_keys(self, values):
        self._out_keys = values

    @property
    def vmap_randomness(self) -> str:
        """TorchRL's :attr:`~torchrl.objectives.LossModule.vmap_randomness`, ``"different"`` where this loss draws
        random numbers itself: a maximiser that samples (``maximiser="sampled"``) or target policy smoothing
        (``policy_noise``); otherwise TorchRL's detection of random modules in the networks."""
        if self._vmap_randomness is None and (getattr(self.maximiser, "draws_random", False)
                                              or self.policy_noise is not None):
            self._vmap_randomness = "different"
        return LossModule.vmap_randomness.fget(self)

    # ---------------------------------------------------------------- pieces
    def _network_facts(self) -> tuple[int | None, torch.dtype | None]:
        """``(input width, parameter dtype)`` of the value network (cached per network): what the batch's inputs must
        add up to and be cast to."""
        cache = self.__dict__.get("_cache_facts")
        if cache is None or cache[0] is not self.value_network:
            floats = [p for p in self.value_network_params.values(True, True) if p.is_floating_point()]
            cache = (self.value_network, input_width(self.value_network), floats[0].dtype if floats else None)
            self.__dict__["_cache_facts"] = cache
        return cache[1], cache[2]

    def _network_call(self, name: str) -> NetworkCall:
        """The :class:`~torchrl_wbrm.objectives._fast.NetworkCall` of ``"value_network"``, ``"actor_network"`` (or a
        subclass's ``"critic_network"``), cached per network and :attr:`fast_path`."""
        network = getattr(self, name)
        cache = self.__dict__.setdefault("_cache_network_calls", {})
        entry = cache.get(name)
        if entry is None or entry[0] is not network or entry[1] != self.fast_path:
            call = NetworkCall(network, getattr(self, f"{name}_params"), self._out_key(name),
                               why=f"the {name.replace('_', ' ')}'s output", direct=self.fast_path)
            entry = cache[name] = (network, self.fast_path, call)
        return entry[2]

    def _out_key(self, name: str) -> NestedKey:
        """The output read from the network ``name``."""
        if name == "actor_network":
            return self.tensor_keys.action
        return self.tensor_keys.action_value if self.discrete else self.tensor_keys.state_action_value

    def _call(self, name: str, params, inputs, batch_size, *, detach: bool = False) -> torch.Tensor:
        """How every method calls a network: network ``name`` with ``params`` on the tensors ``inputs`` (its
        in_keys -> tensors of leading shape ``batch_size``); ``detach``: no gradient to the parameters.

        The value network with ``num_qvalue_nets`` K > 1 critics (parameters stacked along a first dimension, as
        TorchRL's ``convert_to_functional(..., expand_dim=K)``): each critic evaluated by one ``torch.vmap`` over the
        stacked parameters, the output of shape ``[K, *batch_size, ...]``."""
        call = self._network_call(name)
        if name != "value_network" or self.num_qvalue_nets == 1:
            return call(params, inputs, batch_size, detach=detach)
        return torch.vmap(lambda p: call(p, inputs, batch_size, detach=detach),
                          randomness=self.vmap_randomness)(named_tensors(params))

    def _min_q(self, params, inputs, batch_size) -> torch.Tensor:
        """Q on ``inputs``; with K > 1 critics, the minimum over them (TD3's clipped double-Q)."""
        output = self._call("value_network", params, inputs, batch_size)
        return output if self.num_qvalue_nets == 1 else output.amin(0)

    def _entries(self, tensordict: TensorDictBase, keys, why: str) -> dict:
        """``{key: tensordict[key]}`` for ``keys`` (a KeyError naming a missing key and ``why``)."""
        return {key: get_entry(tensordict, key, why) for key in keys}

    def _target(self, tensordict: TensorDictBase, next_value: torch.Tensor) -> torch.Tensor:
        """``Y = r + γ (1 − terminated) · next_value`` (:func:`~torchrl_wbrm.objectives.functional.bellman_target`)
        with the value estimator's keys and γ (``γ^k`` where the batch holds ``steps_to_next_obs`` ``k``)."""
        estimator = self.value_estimator
        keys = estimator.tensor_keys
        reward = tensordict.get(_next(keys.reward), None)
        if estimator.gamma.device != reward.device:
            estimator.gamma = estimator.gamma.to(reward.device)
        gamma = estimator.gamma
        steps = tensordict.get(keys.steps_to_next_obs, None)
        if steps is not None:
            gamma = gamma ** steps.view_as(reward)
        done = tensordict.get(_next(keys.done), None)
        terminated = tensordict.get(_next(keys.terminated), done)
        return bellman_target(reward, next_value.reshape(reward.shape), terminated, gamma)

    def _weight(self, tensordict: TensorDictBase, check: bool = True) -> torch.Tensor:
        """The per-sample weight, shape ``[*B]`` (detached: the weights are fixed in stage 2), from
        :func:`~torchrl_wbrm.objectives.functional.per_sample_weight`: ŵ (``use_weights``) times the
        ``"priority_weight"`` entry where TorchRL's convention reads it, or ones when neither applies.

        ``check=False`` leaves ŵ's sign check to the caller (:meth:`bellman_error` with ``weight_to_check``)."""
        weight = _product(self._density_ratio(tensordict, check=check), self._priority_weight(tensordict))
        if weight is None:
            reward = get_entry(tensordict, _next(self.tensor_keys.reward), "the reward")
            return torch.ones(tensordict.batch_size, device=reward.device, dtype=reward.dtype)
        return weight

    def _density_ratio(self, tensordict: TensorDictBase, check: bool = True) -> torch.Tensor | None:
        """ŵ, shape ``[*B]``, detached (``None`` with ``use_weights=False``); checked finite and non-negative where
        ``check`` and ``check_inputs`` (:func:`~torchrl_wbrm.objectives.functional.per_sample_weight`)."""
        if not self.use_weights:
            return None
        return per_sample_weight(
            tensordict, self.tensor_keys.weight, dtype=self._network_facts()[1],
            check_weight=check and self.check_inputs,
            why="the per-sample weight ŵ(x, a): write the ratio network's output there, or build the loss with "
                "use_weights=False",
        )

    def _priority_weight(self, tensordict: TensorDictBase) -> torch.Tensor | None:
        """TorchRL's ``"priority_weight"`` p, shape ``[*B]``, where ``use_prioritized_weights`` reads it and the batch
        holds it (``None`` otherwise)."""
        if not self._reads_priority(tensordict):
            return None
        return per_sample_weight(tensordict, None, self.tensor_keys.priority_weight, dtype=self._network_facts()[1],
                                 check_priority=self.check_inputs)

    def _validity_mask(self, tensordict: TensorDictBase, like: torch.Tensor) -> torch.Tensor | None:
        """TorchRL's validity mask of the batch (``("collector", "mask")`` and ``"shifted_valid"``, per
        ``loss_mask_key``; the rule of :meth:`~torchrl.objectives.LossModule._reduce_loss`), of ``like``'s shape, or
        ``None`` where the batch holds none."""
        mask = None
        for key in self._loss_mask_keys():
            value = tensordict.get(key, None)
            if value is not None:
                value = self._expand_loss_mask(value, like)
                mask = value if mask is None else mask & value
        return mask

    def _chosen_q(self, tensordict: TensorDictBase) -> torch.Tensor:
        """Q(x, a) at the data's actions, shape ``[*B]`` (``[K, *B]`` with K > 1 critics), with the online
        parameters (differentiable)."""
        batch = tensordict.batch_size
        keys = self._observation_keys if self.discrete else self.value_network.in_keys
        output = self._call("value_network", self.value_network_params,
                            self._entries(tensordict, keys, "an input of the value network"), batch)
        critics = () if self.num_qvalue_nets == 1 else (self.num_qvalue_nets,)
        if not self.discrete:
            return per_sample(output, torch.Size([*critics, *batch]), self.tensor_keys.state_action_value)
        action = get_entry(tensordict, self.tensor_keys.action, "the action taken in the data")
        num_actions = output.shape[-1]
        if action.shape == (*batch, num_actions):  # one-hot
            return (output * action.to(output.dtype)).sum(-1)
        if action.shape in (batch, (*batch, 1)) and not action.is_floating_point():  # indices
            if checks_run(self.check_inputs, action) and action.device.type == "cpu" and action.numel():
                low, high = (int(v) for v in torch.aminmax(action.long()))
                if low < 0 or high >= num_actions:
                    raise ValueError(
                        f"Entry {self.tensor_keys.action!r} holds action indices from {low} to {high}; the Q head has "
                        f"{num_actions} actions, so indices must lie in [0, {num_actions - 1}]."
                    )
            index = action.reshape(*batch, 1).long().expand(*output.shape[:-1], 1)
            return output.gather(-1, index).squeeze(-1)
        raise ValueError(
            f"Entry {self.tensor_keys.action!r} has shape {tuple(action.shape)} and dtype {action.dtype}; a Q head "
            f"over {num_actions} actions expects one-hot actions {(*batch, num_actions)} or integer indices "
            f"{tuple(batch)} / {(*batch, 1)}."
        )

    def _actor_action(self, tensordict: TensorDictBase, params) -> torch.Tensor:
        """μ(x) with the given actor parameters."""
        inputs = self._entries(tensordict, self.actor_network.in_keys, "an input of the actor")
        return self._call("actor_network", params, inputs, tensordict.batch_size)

    def next_state_value(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``max_{a'} Q(x', a')``, shape ``[*B]``: with the target parameters (``delay_value``) or the online ones,
        under no_grad (semi-gradient, TorchRL's meaning of both) or, with ``residual_gradient``, with the gradient.
        With K > 1 critics, Q is the minimum over them; with ``policy_noise``, the actor's μ'(x') is smoothed as TD3
        does: ``clamp(μ'(x') + clamp(σ ε, −c, c), low, high)``, ``ε ~ N(0, I)``.

        The maximiser's :meth:`~torchrl_wbrm.modules.maximisers.ActionMaximiser.maximise` computes it, with Q
        called through :meth:`_call`."""
        next_td = get_entry(tensordict, "next", "the sub-TensorDict of next states")
        batch = next_td.batch_size
        observations = self._entries(next_td, self._observation_keys, "a next-state input of the value network")
        actor_action = None
        if self.has_actor:
            with torch.no_grad():  # the value loss never trains the actor
                actor_action = self._actor_action(next_td, self.target_actor_network_params)
                if self.policy_noise is not None:  # TD3's target policy smoothing
                    noise = (torch.randn_like(actor_action) * self.policy_noise).clamp(-self.noise_clip,
                                                                                        self.noise_clip)
                    actor_action = (actor_action + noise).clamp(self.min_action, self.max_action)
        params = self.target_value_network_params if self.delay_value else self.value_network_params

        def q(inputs, batch_shape):
            return self._min_q(params, inputs, batch_shape)

        with nullcontext() if self.residual_gradient else torch.no_grad():
            return self.maximiser.maximise(q, observations, batch, action_key=self.tensor_keys.action,
                                           actor_action=actor_action)

    # ---------------------------------------------------------------- input checks
    def _checked_inputs(self, tensordict: TensorDictBase, weight_to_check: torch.Tensor | None = None) -> TensorDictBase:
        """Check a batch against the documented shapes before any network sees it; return it with bool flags.

        The checks of values (finite, signs, 0/1 flags; host reads) run where
        :func:`~torchrl_wbrm.objectives._utils.checks_run` says so: with ``check_inputs`` (default), outside
        ``torch.compile``, on a batch no functorch transform wraps; the checks of keys, shapes and dtypes always run.
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
        run = checks_run(self.check_inputs, tensordict.get(_next(self.tensor_keys.reward), None))
        flags = {}
        checks: list[tuple[torch.Tensor, NestedKey]] = []
        reward_shape = None
        for key, why in ((self.tensor_keys.reward, "the reward"), (self.tensor_keys.done, "episode-end flag"),
                         (self.tensor_keys.terminated, "episode-end flag; no bootstrap where it is True")):
            value = per_sample(get_entry(tensordict, _next(key), why), batch, _next(key))
            if key == self.tensor_keys.reward:
                checks.append((value, _next(key)))
                reward_shape = tensordict.get(_next(key), None).shape
            else:
                raw = tensordict.get(_next(key), None)
                flag = as_bool_flag(raw, _next(key), check=run)
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
        if run and not _finite_and_non_negative([v for v, _ in checks], weight_to_check):
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

        ``Y`` carries a gradient exactly when the bootstrap is by residual gradient (``residual_gradient=True``).
        Shared by :meth:`value_loss` and by subclasses (:class:`~torchrl_wbrm.objectives.MABOLoss`).
        ``weight_to_check``: ŵ, checked with the batch's entries (see :meth:`_checked_inputs`).
        """
        tensordict = self._checked_inputs(tensordict, weight_to_check)
        q_value = self._chosen_q(tensordict)
        next_value = self.next_state_value(tensordict)
        target_value = self._target(tensordict, next_value)
        return q_value, per_sample(target_value, tensordict.batch_size, _next(self.tensor_keys.reward))

    def value_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The weighted Bellman residual (:func:`~torchrl_wbrm.objectives.functional.weighted_bellman_residual`);
        returns ``(loss, diagnostics)``.

        The diagnostics include the detached per-sample ``"td_error"`` (δ²), which :meth:`forward` writes back.
        """
        density_ratio = self._density_ratio(tensordict, check=False)
        run = checks_run(self.check_inputs, density_ratio)
        priority = self._priority_weight(tensordict)
        q_value, target_value = self.bellman_error(tensordict, density_ratio if run else None)
        if run and density_ratio is not None and density_ratio.device.type == "cpu":
            if not bool(_product(density_ratio, priority).any()):
                raise ValueError(
                    f"Every weight of the batch is 0 (entry {self.tensor_keys.weight!r}"
                    f"{', times ' + repr(self.tensor_keys.priority_weight) if priority is not None else ''}): "
                    "the weighted residual would be 0 and its effective sample size undefined. Check the stored "
                    "weights (a collapsed density ratio?) or sample larger batches."
                )
        # ŵ inside the per-sample term (the paper's mean) or in the reduction's weights (self-normalised); TorchRL's
        # priority weight always in the reduction's weights, Σ pᵢ lᵢ / Σ pᵢ
        weight, reduce_weight = density_ratio, priority
        if self.weight_reduction == "normalised":
            weight, reduce_weight = None, _product(density_ratio, priority)
        if weight is None:
            weight = torch.ones_like(target_value)
        per_sample_loss = weighted_bellman_residual(
            q_value,
            target_value,
            weight,
            residual=self.residual,
            reduction="none",
        )
        if self.num_qvalue_nets > 1:  # TD3: the critics' terms summed
            per_sample_loss = per_sample_loss.sum(0)
        loss = self._reduce_loss(per_sample_loss, tensordict, weights=reduce_weight)
        if self.residual == "absolute_mean" and self.reduction != "none":
            loss = loss.abs()
        with torch.no_grad():
            td_error = bellman_residual(q_value, target_value)
            mask = self._validity_mask(tensordict, target_value)
            squared = td_error.pow(2)
            diagnostics = {
                "td_error": squared if self.num_qvalue_nets == 1 else squared.amax(0),
                "td_error_mean": _masked_mean(td_error, mask),
                "td_error_abs_mean": _masked_mean(td_error.abs(), mask),
                "q_mean": _masked_mean(q_value, mask),
                "target_value_mean": _masked_mean(target_value, mask),
            }
            if self.use_weights:
                weights = _product(density_ratio, priority)
                if mask is not None:
                    weights = torch.where(mask, weights, torch.zeros_like(weights))
                diagnostics["weight_mean"] = _masked_mean(weights, mask)
                diagnostics[WEIGHT_ESS] = effective_sample_size(weights)
        return loss, diagnostics

    def _reads_priority(self, tensordict: TensorDictBase) -> bool:
        """Whether the batch's ``"priority_weight"`` is read (TorchRL's ``use_prioritized_weights`` convention; never
        when it is the ŵ entry itself)."""
        key = getattr(self.tensor_keys, "priority_weight", None)
        if key is None:
            return False
        return (self.use_prioritized_weights in (True, "auto") and not (self.use_weights and key == self.tensor_keys.weight)
                and tensordict.get(key, None) is not None)

    def actor_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """``−mean_i Q(x_i, μ(x_i))`` (Q frozen), optionally ŵ-weighted and with TD3+BC's cloning term.

        Only the actor receives gradients. Returns ``(loss, diagnostics)``.
        """
        if not self.has_actor:
            raise ValueError("actor_loss needs an actor_network; this loss was built without one.")
        key = self.tensor_keys.state_action_value
        batch = tensordict.batch_size
        mu = self._actor_action(tensordict, self.actor_network_params)
        q_inputs = self._entries(tensordict, self._observation_keys, "an input of the value network")
        q_inputs[self.tensor_keys.action] = mu
        params = self.value_network_params if self.num_qvalue_nets == 1 else self.value_network_params[0]
        q_actor = per_sample(self._network_call("value_network")(params, q_inputs, batch, detach=True), batch, key)
        per_sample_loss = -q_actor
        diagnostics = {"actor_q_mean": q_actor.detach().mean(), "actor_q_abs_mean": q_actor.detach().abs().mean()}
        if self.bc_alpha is not None:
            action = get_entry(tensordict, self.tensor_keys.action, "the dataset action for behaviour cloning")
            if action.shape != mu.shape:
                raise ValueError(
                    f"Entry {self.tensor_keys.action!r} has shape {tuple(action.shape)} but the actor writes "
                    f"{tuple(mu.shape)}."
                )
            bc = (mu - action).pow(2).reshape(*tensordict.batch_size, -1).mean(-1)
            per_sample_loss = td3bc_lambda(self.bc_alpha, q_actor) * per_sample_loss + bc
            diagnostics["bc_loss"] = bc.detach().mean()
        weight = self._density_ratio(tensordict) if self.weight_actor_loss else None
        reduce_weight = self._priority_weight(tensordict)
        if self.weight_reduction == "normalised":
            weight, reduce_weight = None, _product(weight, reduce_weight)
        if weight is not None:
            per_sample_loss = per_sample_loss * weight
        return self._reduce_loss(per_sample_loss, tensordict, weights=reduce_weight), diagnostics

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
