"""A per-sample weight ŵ for any TorchRL loss whose terms are per sample: :class:`WeightedLoss`."""
from __future__ import annotations

import inspect
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import dispatch
from tensordict.utils import NestedKey
from torchrl.objectives.common import AUTO_LOSS_MASK_KEYS, LossModule

from torchrl_wbrm.keys import DENSITY_RATIO, PRIORITY_WEIGHT, WEIGHT_ESS
from torchrl_wbrm.objectives._utils import check_reduction, checks_run, per_sample
from torchrl_wbrm.objectives.functional import effective_sample_size, per_sample_weight, weighted_reduce

__all__ = ["NATIVE_PRIORITY_WEIGHT_LOSSES", "WeightedLoss", "reads_priority_weight"]

#: The losses of torchrl 0.14.1 that read ``"priority_weight"`` themselves (``LossModule._maybe_get_priority_weight``
#: or their ``priority_weight`` key) and reduce their terms as ``Σ pᵢ lᵢ / Σ pᵢ``. Every other loss (``IQLLoss``,
#: ``DiscreteIQLLoss``, ``CQLLoss``, ``DiscreteCQLLoss``, ``BCLoss``, ``REDQLoss``, ``CrossQLoss``, ``PPOLoss``, ...)
#: ignores that entry: weight it with :class:`WeightedLoss`. ``tests/test_weighted_loss.py`` derives this list from
#: torchrl's source and checks it against the losses' behaviour.
NATIVE_PRIORITY_WEIGHT_LOSSES = (
    "DDPGLoss", "DQNLoss", "DiscreteSACLoss", "DistributionalDQNLoss", "SACLoss", "TD3BCLoss", "TD3Loss", "TQCLoss",
)

#: ``loss_*`` terms that torchrl computes from the whole batch even with ``reduction="none"``, by loss class: the
#: weighted mean applies to their per-sample part only (see :class:`WeightedLoss`).
_BATCH_COUPLED_TERMS = {
    "TD3BCLoss": {
        "loss_actor": "its behaviour-cloning term is F.mse_loss over the whole batch and its λ = α / mean|Q| a batch "
                      "statistic; only the −λ·Q(x, μ(x)) part is per sample",
    },
}


def reads_priority_weight(loss: LossModule) -> bool:
    """Whether ``loss`` multiplies its per-sample terms by the batch's ``"priority_weight"`` itself: a torchrl
    loss with a ``priority_weight`` key whose code reads it (``_maybe_get_priority_weight`` or
    ``tensor_keys.priority_weight``), with ``use_prioritized_weights`` ``True`` or ``"auto"``."""
    if "priority_weight" not in getattr(getattr(type(loss), "default_keys", None), "__dataclass_fields__", {}):
        return False
    if getattr(loss, "use_prioritized_weights", False) not in (True, "auto"):
        return False
    for klass in type(loss).__mro__:
        if klass is LossModule or not issubclass(klass, LossModule):
            continue
        try:
            source = inspect.getsource(klass)
        except (OSError, TypeError):  # no source (a class built at run time): trust the key
            return True
        if "_maybe_get_priority_weight" in source or "tensor_keys.priority_weight" in source:
            return True
    return False


def _is_loss_term(key) -> bool:
    return isinstance(key, str) and (key == "loss" or key.startswith("loss_"))


class WeightedLoss(LossModule):
    r"""Any TorchRL loss whose terms are per sample, reduced as a ŵ-weighted mean ``Σ wᵢ lᵢ / Σ wᵢ``.

    The wrapped ``loss`` may be built with any reduction (TorchRL's default ``"mean"`` included):
    :class:`WeightedLoss` sets its ``reduction`` to ``"none"`` (TorchRL reads ``self.reduction`` when the loss
    reduces its terms, at every ``forward``), so that each of its ``"loss"`` / ``"loss_*"`` entries holds one value
    per sample, ``lᵢ``; the wrapped loss keeps that setting afterwards. Where such a loss has a
    ``scalar_output_mode`` left unset, it becomes ``"exclude"`` (what TorchRL picks for ``reduction="none"``: the
    scalars ``"alpha"`` and ``"entropy"`` are left out of the output). :class:`WeightedLoss` reads the per-sample
    weight ``wᵢ`` from the batch (``"density_ratio"``, e.g. the stage-1 ŵ stored by
    :func:`~torchrl_wbrm.ratio.store_density_ratio`; :func:`~torchrl_wbrm.objectives.functional.per_sample_weight`)
    and reduces every such entry the way TorchRL reduces a ``"priority_weight"``
    (:func:`~torchrl_wbrm.objectives.functional.weighted_reduce`): ``Σ wᵢ lᵢ / Σ wᵢ`` (``reduction="mean"``),
    ``Σ wᵢ lᵢ`` (``"sum"``) or ``wᵢ lᵢ`` (``"none"``). An entry with event dimensions past the batch (``BCLoss``'s
    elementwise ``[B, action_dim]``) is first averaged (summed, for ``"sum"``) over them, as the wrapped loss's own
    ``"mean"`` (``"sum"``) would. With constant weights the result is the unwrapped loss; with 0/1 weights it is the
    loss on the rows of weight 1.

    Which torchrl losses need it: in torchrl 0.14.1 only ``DDPGLoss``, ``DQNLoss``, ``DistributionalDQNLoss``,
    ``SACLoss``, ``DiscreteSACLoss``, ``TD3Loss``, ``TD3BCLoss`` and ``TQCLoss`` read ``"priority_weight"``
    themselves (:data:`NATIVE_PRIORITY_WEIGHT_LOSSES`); ``IQLLoss``, ``CQLLoss``, ``DiscreteCQLLoss``, ``BCLoss`` and
    the others ignore it, so a weight stored there leaves them unweighted. :class:`WeightedLoss` weights either kind
    the same way.

    The priority weight: a ``"priority_weight"`` entry in the batch (a prioritized replay buffer's importance weights)
    multiplies ŵ, ``wᵢ = ŵᵢ pᵢ`` (``use_prioritized_weights``, TorchRL's convention; ``"auto"`` by default, ``False``
    ignores it). To weight no sample twice, the wrapped loss's own ``use_prioritized_weights`` is set to ``False``:
    a loss that reads ``"priority_weight"`` natively then returns unweighted per-sample terms, and the product is
    applied once, here, to every term.

    Entries that pass through unchanged (not per sample): every entry other than ``"loss"`` / ``"loss_*"`` (the
    diagnostics, e.g. ``"td_error"``, ``"pred_value"``, ``"target_value"``, ``"next_state_value"``, ``"lmbd"``,
    ``"bc_loss"``, and the scalars a loss adds with ``scalar_output_mode="non_tensor"``, ``"alpha"`` and
    ``"entropy"``). Every ``loss_*`` entry of torchrl 0.14.1's losses is per sample with ``reduction="none"``,
    including the entropy coefficient's ``"loss_alpha"`` of ``SACLoss`` and ``CQLLoss`` (``−log α (log π(a|x) +
    H̄)`` per sample, so it is weighted too), except:

    - ``CQLLoss(with_lagrange=True)``'s ``"loss_alpha_prime"``, a batch-level Lagrange term: refused at
      construction (torchrl cannot compute it with ``reduction="none"``);
    - ``TD3BCLoss``'s ``"loss_actor"``: its behaviour-cloning term is a batch mean and its λ = α / mean|Q| a batch
      statistic (both unweighted, as in torchrl); only ``−λ Q(x, μ(x))`` is weighted per sample. For a fully
      ŵ-weighted TD3+BC use :class:`~torchrl_wbrm.objectives.WeightedBellmanLoss` with ``bc_alpha``.

    A ``loss_*`` entry that comes out without the batch's leading shape is refused by name at the first
    ``forward``. Rows that the wrapped loss's validity mask marks invalid (torchrl's ``loss_mask_key``:
    ``("collector", "mask")`` and ``"shifted_valid"`` by default) get weight 0, as torchrl's own reduction drops
    them.

    Args:
        loss (LossModule): the TorchRL loss, with any ``reduction``: it is switched to ``"none"`` here. (Built with
            ``reduction="none"``, ``IQLLoss``, ``CQLLoss`` and ``SACLoss`` also want ``scalar_output_mode="exclude"``
            or ``"non_tensor"`` to silence their warning; built with the default, they need nothing.)

    Keyword Args:
        weight_key (NestedKey): where the per-sample weight is read (shape ``[*B]`` or ``[*B, 1]``, finite,
            ``>= 0``, not all zero). Defaults to ``"density_ratio"``; ``set_keys(weight=...)`` changes it.
        use_prioritized_weights (bool or "auto"): multiply by the batch's ``"priority_weight"`` where present.
            Defaults to the wrapped loss's setting (``"auto"``).
        reduction (str, optional): ``"mean"`` (default, also for ``None``), ``"sum"`` or ``"none"``.

    The wrapper holds no state of its own: its parameters, buffers and sub-modules (the ``*_params`` and
    ``target_*_params``) are the wrapped loss's, so ``state_dict()`` is the wrapped loss's and
    :class:`~torchrl.objectives.SoftUpdate` / :class:`~torchrl.objectives.HardUpdate` built on the wrapper update the
    wrapped loss's targets. ``set_keys`` sets ``weight`` and ``priority_weight`` here and forwards every other key to
    the wrapped loss; ``make_value_estimator`` and ``value_estimator`` are the wrapped loss's; other attributes
    (``actor_network``, ``loss_function``, ...) are read from it. The wrapped loss itself is :attr:`loss_module`.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Bounded
        >>> from torchrl.modules import MLP, ValueOperator
        >>> from torchrl.objectives import IQLLoss, SoftUpdate
        >>> from torchrl_wbrm.modules import make_q_network, make_tanh_normal_actor
        >>> from torchrl_wbrm.objectives import WeightedLoss
        >>> spec = Bounded(-1.0, 1.0, (1,))
        >>> actor = make_tanh_normal_actor(2, spec, num_cells=(16,))
        >>> qvalue = make_q_network(2, 1, num_cells=(16,), initial_bias=0.0)
        >>> value = ValueOperator(MLP(in_features=2, out_features=1, num_cells=(16,)), in_keys=["observation"])
        >>> loss = WeightedLoss(IQLLoss(actor, qvalue, value), weight_key="density_ratio")
        >>> loss.loss_module.reduction  # the wrapped loss gives per-sample terms
        'none'

        >>> loss.make_value_estimator(gamma=0.9)
        >>> updater = SoftUpdate(loss, tau=0.005)
        >>> n = 8
        >>> data = TensorDict({
        ...     "observation": torch.randn(n, 2), "action": spec.rand((n,)),
        ...     "density_ratio": torch.rand(n),
        ...     ("next", "observation"): torch.randn(n, 2), ("next", "reward"): torch.randn(n, 1),
        ...     ("next", "done"): torch.zeros(n, 1, dtype=torch.bool),
        ...     ("next", "terminated"): torch.zeros(n, 1, dtype=torch.bool),
        ... }, [n])
        >>> out = loss(data)
        >>> sorted(out.keys())
        ['loss_actor', 'loss_qvalue', 'loss_value', 'weight_ess']
        >>> (out["loss_actor"] + out["loss_qvalue"] + out["loss_value"]).backward()
        >>> updater.step()
    """

    @dataclass
    class _AcceptedKeys:
        """Maintains default values for all configurable tensordict keys.

        This class defines which tensordict keys can be set using '.set_keys(key_name=key_value)' and their
        default values. Keys of the wrapped loss are set on it through the same ``set_keys``.

        Attributes:
            weight (NestedKey): The input key of the per-sample weight ŵ. Defaults to ``"density_ratio"``.
            priority_weight (NestedKey): The input key of TorchRL's per-sample (importance) weight, multiplied with
                ŵ when present. Defaults to the wrapped loss's ``priority_weight`` key, else ``"priority_weight"``.
        """

        weight: NestedKey = DENSITY_RATIO
        priority_weight: NestedKey = PRIORITY_WEIGHT

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys

    def __init__(
        self,
        loss: LossModule,
        weight_key: NestedKey = DENSITY_RATIO,
        *,
        use_prioritized_weights: str | bool | None = None,
        reduction: str | None = None,
    ) -> None:
        name = type(loss).__name__
        if not isinstance(loss, LossModule):
            raise TypeError(f"WeightedLoss wraps a torchrl LossModule, got {name}.")
        if isinstance(loss, WeightedLoss):
            raise TypeError("The loss is already a WeightedLoss; multiply the weights into one key instead.")
        if not hasattr(loss, "reduction"):
            raise ValueError(
                f"{name} has no 'reduction' setting, so its terms cannot be computed per sample; WeightedLoss needs a "
                "loss that supports reduction='none'."
            )
        check_reduction(loss.reduction)
        if name == "CQLLoss" and getattr(loss, "with_lagrange", False):
            raise ValueError(
                "CQLLoss(with_lagrange=True) has a batch-level term, 'loss_alpha_prime' (the Lagrange multiplier's "
                "loss on the batch mean of the conservative gap), which has no per-sample form: WeightedLoss cannot "
                "weight it. Use with_lagrange=False (a fixed min_q_weight)."
            )
        if use_prioritized_weights is None:
            use_prioritized_weights = getattr(loss, "use_prioritized_weights", "auto")
        if use_prioritized_weights not in (True, False, "auto"):
            raise ValueError(f"use_prioritized_weights must be True, False or 'auto', got {use_prioritized_weights!r}.")
        reduction = check_reduction(reduction)
        super().__init__()
        # one state with the wrapped loss: the same parameters, buffers and (target) parameter modules
        for slot in ("_parameters", "_buffers", "_modules", "_non_persistent_buffers_set"):
            self.__dict__[slot] = loss.__dict__[slot]
        self.__dict__["_has_update_associated"] = loss._has_update_associated
        self.__dict__["_wrapped"] = loss
        self.reduction = reduction
        self.use_prioritized_weights = use_prioritized_weights
        self.batch_coupled_terms = dict(_BATCH_COUPLED_TERMS.get(name, {}))
        loss.use_prioritized_weights = False  # the product ŵ·p is applied here, once
        loss.reduction = "none"  # per-sample terms: TorchRL's losses read self.reduction when they reduce
        if hasattr(loss, "scalar_output_mode") and loss.scalar_output_mode is None:
            loss.scalar_output_mode = "exclude"  # TorchRL's choice for reduction="none" (its warning's default)
        inner_priority = getattr(getattr(loss, "tensor_keys", None), "priority_weight", None)
        super().set_keys(weight=weight_key)
        if inner_priority is not None:
            super().set_keys(priority_weight=inner_priority)

    # ---------------------------------------------------------------- the wrapped loss
    @property
    def loss_module(self) -> LossModule:
        """The wrapped loss (its ``reduction`` set to ``"none"``)."""
        return self.__dict__["_wrapped"]

    def __getattr__(self, item):
        try:
            return super().__getattr__(item)
        except AttributeError:
            wrapped = self.__dict__.get("_wrapped")
            if wrapped is None:
                raise
            return getattr(wrapped, item)

    def _apply(self, fn, *args, **kwargs):
        # the state is the wrapped loss's: ``to()``, ``double()``, ... go through it (once), erasing its caches
        self._erase_cache()
        self.loss_module._apply(fn, *args, **kwargs)
        return self

    def train(self, mode: bool = True):
        self.loss_module.train(mode)
        self.training = mode
        return self

    def set_keys(self, **kwargs) -> None:
        """Set ``weight`` / ``priority_weight`` here and every other key on the wrapped loss (which refuses the keys
        it does not know, naming them)."""
        own = {key: kwargs.pop(key) for key in list(kwargs) if key in self._AcceptedKeys.__dataclass_fields__}
        if kwargs:
            self.loss_module.set_keys(**kwargs)
        if own:
            super().set_keys(**own)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def make_value_estimator(self, value_type=None, **hyperparams):
        """The wrapped loss's :meth:`~torchrl.objectives.LossModule.make_value_estimator`."""
        return self.loss_module.make_value_estimator(value_type, **hyperparams)

    @property
    def value_estimator(self):
        return self.loss_module.value_estimator

    @value_estimator.setter
    def value_estimator(self, value):
        self.loss_module.value_estimator = value

    @property
    def in_keys(self) -> list[NestedKey]:
        return list(dict.fromkeys([*self.loss_module.in_keys, self.tensor_keys.weight]))

    @property
    def out_keys(self) -> list[NestedKey]:
        return [*self.loss_module.out_keys, WEIGHT_ESS]

    # ---------------------------------------------------------------- the weights
    def _weight(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``ŵ`` (times ``"priority_weight"`` where present and enabled), shape ``[*B]``, detached; checked finite,
        non-negative and not all zero (CPU tensors)."""
        batch = tensordict.batch_size
        key = self.tensor_keys.weight
        priority_key = self.tensor_keys.priority_weight
        reads_priority = self.use_prioritized_weights in (True, "auto") and priority_key != key
        weight = per_sample_weight(
            tensordict, key, priority_key if reads_priority else None,
            why="the per-sample weight of WeightedLoss: store it there (e.g. store_density_ratio(buffer, "
                "ratio_network=..., key=...)) or set_keys(weight=...)",
        )
        source = repr(key)
        if reads_priority and tensordict.get(priority_key, None) is not None:
            source = f"{key!r} times {priority_key!r}"
        # torchrl's validity masks (the wrapped loss's public loss_mask_key, read by torchrl's rule): weight 0 where False
        setting = getattr(self.loss_module, "loss_mask_key", None)
        for mask_key in () if setting is None else AUTO_LOSS_MASK_KEYS if setting == "auto" else (setting,):
            mask = tensordict.get(mask_key, None)
            if mask is not None:
                weight = weight * per_sample(mask, batch, mask_key).to(weight.dtype)
                source += f" masked by {mask_key!r}"
        if checks_run(True, weight) and weight.device.type == "cpu" and not bool(weight.sum() > 0):
            raise ValueError(
                f"Every weight of the batch is 0 (entry {source}): the weighted mean Σ wᵢ lᵢ / Σ wᵢ is undefined. "
                "Check the stored weights (a collapsed density ratio?) or sample larger batches."
            )
        return weight

    def _per_sample(self, value: torch.Tensor, key: str, batch: torch.Size) -> torch.Tensor:
        """A loss term of shape ``[*B, *event]`` as ``[*B]``: event dimensions averaged (summed for ``"sum"``)."""
        if value.shape[: len(batch)] != batch:
            raise ValueError(
                f"{type(self.loss_module).__name__} returned {key!r} of shape {tuple(value.shape)} with reduction='none', "
                f"not one value per sample of the batch {tuple(batch)}: WeightedLoss cannot weight it."
            )
        if value.ndim == len(batch):
            return value
        flat = value.reshape(*batch, -1)
        return flat.sum(-1) if self.reduction == "sum" else flat.mean(-1)

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The wrapped loss's entries, each ``"loss"`` / ``"loss_*"`` term reduced with the weights, the others as
        they are, and ``"weight_ess"``, the Kish effective sample size ``(Σwᵢ)² / Σwᵢ²`` of the batch's weights."""
        weight = self._weight(tensordict)
        batch = tensordict.batch_size
        terms = self.loss_module(tensordict)
        out = TensorDict({}, batch_size=[])
        for key in terms.keys():
            if _is_loss_term(key):
                value = self._per_sample(terms.get(key), key, batch)
                out.set(key, weighted_reduce(value, weight.to(value.dtype), self.reduction))
            elif terms.is_non_tensor(key):
                out.set_non_tensor(key, terms.get_non_tensor(key))
            else:
                out.set(key, terms.get(key))
        with torch.no_grad():
            out.set(WEIGHT_ESS, effective_sample_size(weight))
        return out
