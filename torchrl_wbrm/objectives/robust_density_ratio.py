"""Stage 1 of WBRM: the robust density-ratio loss (Basu's power divergence), Section 3 of the paper."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import dispatch, TensorDictModule
from tensordict.utils import NestedKey
from torchrl.objectives.common import LossModule

from torchrl_wbrm.keys import BEHAVIOUR, DENSITY_RATIO, DENSITY_RATIO_ESS, EXPERT, LOSS_DENSITY_RATIO
from torchrl_wbrm.objectives._fast import NetworkCall
from torchrl_wbrm.objectives._utils import (
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
)
from torchrl_wbrm.objectives.functional import (
    basu_power_divergence,
    effective_sample_size,
    masked_reduce,
    normalisation_penalty,
    power_divergence_integrands,
)

__all__ = ["RobustDensityRatioLoss", "basu_power_divergence", "power_divergence_integrands"]


class RobustDensityRatioLoss(LossModule):
    r"""Fits ŵ(x, a) ≈ w^e = dP^{π^e}/dP^{π^b} by Basu's power divergence (Section 3, "Density Ratio Estimation").

    Paper (α = ½):  ``R̂_S(w) = mean_{S^b} w^{3/2} − 3 · mean_{S^e} w^{1/2}``; for any α > 0
    ``mean_b w^{1+α} − (1 + 1/α) · mean_e w^α`` (α = 1 is uLSIF) and the KL limit ``mean_b w − mean_e log w``
    (``alpha="kl"``). The equation lives in :func:`~torchrl_wbrm.objectives.functional.basu_power_divergence`. Its population minimiser is the true
    ratio, at which ``E_b ŵ = 1``: the diagnostic ``"density_ratio_behaviour_mean"`` should stay near 1.
    The paper's Assumption 4.1 bounds the ratio in ``[Φ, Ψ]``; :class:`~torchrl_wbrm.modules.DensityRatioNetwork`
    enforces it on the network's output.

    Args:
        ratio_network (TensorDictModule): reads its ``in_keys`` (e.g. ``"observation"``, ``"action"``) and writes a
            strictly positive ratio to ``"density_ratio"`` (shape ``[*B]`` or ``[*B, 1]``).

    Keyword Args:
        alpha (float or "kl"): Basu's power α > 0, or ``"kl"`` for the α → 0 (KL) limit. Defaults to ``0.5``, the
            paper's choice.
        normalisation_coefficient (float): λ ≥ 0 of the penalty ``λ · (mean_den ŵ − 1)²`` (``mean_den`` is the
            behaviour mean, or the β-mixture with ``relative_beta``), added to ``"loss_density_ratio"``.
            Defaults to ``0.0`` (off).
        non_negative_correction (float, optional): the constant C of the non-negative correction of Kato &
            Teshima (D3RE, ICML 2021) against loss hacking; must satisfy ``0 < C < 1/sup w^e``. Defaults to ``None``.
        relative_beta (float): β ∈ [0, 1) of the relative ratio ``p_e / (βp_e + (1 − β)p_b)`` (RuLSIF), bounded by
            1/β. Defaults to ``0.0`` (the plain ratio of the paper).
        reduction (str, optional): ``"mean"`` (default, also for ``None``), ``"sum"`` (sums instead of means), or
            ``"none"``: the per-pair terms ``(1 − β)ψ(ŵ_b,i) + βψ(ŵ_e,i) − φ(ŵ_e,i)``, of the common batch shape of
            ``"behaviour"`` and ``"expert"`` (they must match), whose mean is the ``"mean"`` loss. ``"none"`` cannot
            be combined with the normalisation penalty or the non-negative correction (both act on means).

    The input TensorDict holds two sub-TensorDicts, ``"behaviour"`` (samples S^b of P^{π^b}) and ``"expert"``
    (samples S^e of P^{π^e}), each with the ratio network's ``in_keys``; their batch sizes may differ (except for
    ``reduction="none"``). The input is not modified.

    Output: ``"loss_density_ratio"`` and detached diagnostics ``"density_ratio_behaviour_mean"`` (≈ 1 at the
    optimum), ``"density_ratio_expert_mean"``, ``"density_ratio_min"``, ``"density_ratio_max"`` (over both sets),
    ``"density_ratio_ess"`` (Kish effective sample size (Σŵ)²/Σŵ² on the behaviour batch) and
    ``"normalisation_penalty"`` (the unscaled ``(mean_den ŵ − 1)²``).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_wbrm.modules import DensityRatioNetwork
        >>> from torchrl_wbrm.objectives import RobustDensityRatioLoss
        >>> ratio = DensityRatioNetwork(3, 1, bounds=(0.01, 100.0), num_cells=(32,))
        >>> loss = RobustDensityRatioLoss(ratio, alpha=0.5)
        >>> data = TensorDict({
        ...     "behaviour": TensorDict({"observation": torch.randn(64, 3), "action": torch.randn(64, 1)}, [64]),
        ...     "expert": TensorDict({"observation": torch.randn(32, 3), "action": 0.1 * torch.randn(32, 1)}, [32]),
        ... }, [])
        >>> out = loss(data)
        >>> sorted(out.keys())
        ['density_ratio_behaviour_mean', 'density_ratio_ess', 'density_ratio_expert_mean', 'density_ratio_max', 'density_ratio_min', 'loss_density_ratio', 'normalisation_penalty']
        >>> out["loss_density_ratio"].backward()
    """

    @dataclass
    class _AcceptedKeys:
        """Maintains default values for all configurable tensordict keys.

        This class defines which tensordict keys can be set using '.set_keys(key_name=key_value)' and their
        default values.

        Attributes:
            behaviour (NestedKey): The input sub-tensordict holding the behaviour samples S^b.
                Defaults to ``"behaviour"``.
            expert (NestedKey): The input sub-tensordict holding the expert samples S^e.
                Defaults to ``"expert"``.
            density_ratio (NestedKey): Where the ratio network writes ŵ. Defaults to ``"density_ratio"``.
        """

        behaviour: NestedKey = BEHAVIOUR
        expert: NestedKey = EXPERT
        density_ratio: NestedKey = DENSITY_RATIO

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    out_keys = [
        LOSS_DENSITY_RATIO,
        "density_ratio_behaviour_mean",
        "density_ratio_expert_mean",
        "density_ratio_min",
        "density_ratio_max",
        DENSITY_RATIO_ESS,
        "normalisation_penalty",
    ]

    ratio_network: TensorDictModule
    ratio_network_params: TensorDictParams
    target_ratio_network_params: TensorDictParams
    #: How :class:`~torchrl_wbrm.objectives._fast.NetworkCall` calls a plain ratio network: on tensors (``True``) or
    #: through a TensorDict and ``to_module`` (``False``); the same computation either way (tested).
    fast_path: bool = True
    #: Check the inputs' and ŵ's values (finite, ŵ > 0; host reads) in eager use. They skip themselves inside
    #: ``torch.compile`` and functorch transforms (``torch.vmap``); ``False`` turns them off everywhere. Every cache
    #: is ``_cache``-named, so a dtype or device move (``.double()``, ``.to(device)``) drops it.
    check_inputs: bool = True

    def __init__(
        self,
        ratio_network: TensorDictModule,
        *,
        alpha: float | str = 0.5,
        normalisation_coefficient: float = 0.0,
        non_negative_correction: float | None = None,
        relative_beta: float = 0.0,
        reduction: str | None = None,
    ) -> None:
        reduction = check_reduction(reduction)
        if alpha != "kl" and not (
            isinstance(alpha, (int, float)) and not isinstance(alpha, bool) and alpha > 0 and math.isfinite(alpha)
        ):
            raise ValueError(f"alpha must be a finite number > 0 or 'kl' (the α → 0 limit), got {alpha!r}.")
        if not normalisation_coefficient >= 0:
            raise ValueError(f"normalisation_coefficient must be >= 0, got {normalisation_coefficient!r}.")
        if non_negative_correction is not None and not non_negative_correction > 0:
            raise ValueError(
                f"non_negative_correction (D3RE's C) must be > 0 (and below 1/sup w), or None; "
                f"got {non_negative_correction!r}."
            )
        if not 0.0 <= relative_beta < 1.0:
            raise ValueError(f"relative_beta must lie in [0, 1), got {relative_beta!r}.")
        if reduction == "none" and (normalisation_coefficient > 0 or non_negative_correction is not None):
            raise ValueError(
                "reduction='none' gives per-pair terms and cannot be combined with normalisation_coefficient > 0 "
                "or non_negative_correction, which act on batch means."
            )
        super().__init__()
        self.convert_to_functional(ratio_network, "ratio_network", create_target_params=False)
        self.alpha = alpha if alpha == "kl" else float(alpha)
        self.normalisation_coefficient = float(normalisation_coefficient)
        self.non_negative_correction = None if non_negative_correction is None else float(non_negative_correction)
        self.relative_beta = float(relative_beta)
        self.reduction = reduction

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self) -> list[NestedKey]:
        def nested(prefix: NestedKey, key: NestedKey) -> tuple:
            prefix = prefix if isinstance(prefix, tuple) else (prefix,)
            return (*prefix, *(key if isinstance(key, tuple) else (key,)))

        return [
            nested(side, key)
            for side in (self.tensor_keys.behaviour, self.tensor_keys.expert)
            for key in self.ratio_network.in_keys
        ]

    def _network_call(self) -> NetworkCall:
        """How the ratio network is called (cached per network and :attr:`fast_path`)."""
        cache = self.__dict__.get("_cache_network_call")
        if cache is None or cache[0] is not self.ratio_network or cache[1] != self.fast_path:
            call = NetworkCall(self.ratio_network, self.ratio_network_params, self.tensor_keys.density_ratio,
                               why=f"the ratio network's output; its out_keys are {self.ratio_network.out_keys}",
                               direct=self.fast_path)
            cache = self.__dict__["_cache_network_call"] = (self.ratio_network, self.fast_path, call)
        return cache[2]

    def _network_facts(self) -> tuple[int | None, torch.dtype | None]:
        """``(input width, parameter dtype)`` of the ratio network (cached per network)."""
        cache = self.__dict__.get("_cache_facts")
        if cache is None or cache[0] is not self.ratio_network:
            floats = [p for p in self.ratio_network_params.values(True, True) if p.is_floating_point()]
            cache = (self.ratio_network, input_width(self.ratio_network), floats[0].dtype if floats else None)
            self.__dict__["_cache_facts"] = cache
        return cache[1], cache[2]

    def density_ratio(self, samples: TensorDictBase, name: str) -> torch.Tensor:
        """ŵ on one set of samples (``name`` is ``"behaviour"`` or ``"expert"`` and only used in error messages)."""
        key = self.tensor_keys.density_ratio
        tensors = [get_entry(samples, k, f"input of the ratio network, in the {name!r} samples")
                   for k in self.ratio_network.in_keys]
        check_not_empty(samples.batch_size, f"{name!r}")
        named = {(name, *(k if isinstance(k, tuple) else (k,))): t for k, t in zip(self.ratio_network.in_keys, tensors)}
        width, dtype = self._network_facts()
        check_input_width(width, named, samples.batch_size, "ratio network")
        check_input_dtype(dtype, named, "ratio network")
        run_checks = checks_run(self.check_inputs, tensors[0] if tensors else None)
        if run_checks:
            for k, t in named.items():
                check_finite(t, k)
        w = self._network_call()(self.ratio_network_params, dict(zip(self.ratio_network.in_keys, tensors)),
                                 samples.batch_size)
        if w.shape not in (samples.batch_size, (*samples.batch_size, 1)):
            raise ValueError(
                f"The ratio network wrote {key!r} with shape {tuple(w.shape)} on {name!r} samples of batch size "
                f"{tuple(samples.batch_size)}; expected {tuple(samples.batch_size)} or {(*samples.batch_size, 1)}."
            )
        if checks_run(self.check_inputs, w):  # the output: batched where the parameters are
            check_sign(w, key, strictly_positive=True)
        return w.reshape(samples.batch_size)

    def density_ratio_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The loss of Section 3 (:func:`~torchrl_wbrm.objectives.functional.basu_power_divergence`) plus options; returns ``(loss, diagnostics)``."""
        behaviour = get_entry(tensordict, self.tensor_keys.behaviour, "sub-TensorDict of behaviour samples S^b")
        expert = get_entry(tensordict, self.tensor_keys.expert, "sub-TensorDict of expert samples S^e")
        if self.reduction == "none" and behaviour.batch_size != expert.batch_size:
            raise ValueError(
                f"reduction='none' pairs behaviour and expert samples, so their batch sizes must match; got "
                f"{tuple(behaviour.batch_size)} and {tuple(expert.batch_size)}."
            )
        for key in self.ratio_network.in_keys:  # both sides must describe the same (x, a)
            prefix = key if isinstance(key, tuple) else (key,)
            b_value, e_value = behaviour.get(key, None), expert.get(key, None)
            if b_value is not None and e_value is not None:
                check_same_features(b_value, e_value, (self.tensor_keys.behaviour, *prefix),
                                    (self.tensor_keys.expert, *prefix), behaviour.batch_size, expert.batch_size)
        w_behaviour = self.density_ratio(behaviour, "behaviour")
        w_expert = self.density_ratio(expert, "expert")
        behaviour_mask, expert_mask = self._validity_mask(behaviour, w_behaviour), self._validity_mask(expert, w_expert)
        loss = basu_power_divergence(
            w_behaviour,
            w_expert,
            alpha=self.alpha,
            relative_beta=self.relative_beta,
            non_negative_correction=self.non_negative_correction,
            reduction=self.reduction,
            behaviour_mask=behaviour_mask,
            expert_mask=expert_mask,
        )
        behaviour_mean = masked_reduce(w_behaviour, "mean", behaviour_mask)
        expert_mean = masked_reduce(w_expert, "mean", expert_mask)
        penalty = normalisation_penalty(behaviour_mean, expert_mean, self.relative_beta)
        if self.normalisation_coefficient > 0:
            loss = loss + self.normalisation_coefficient * penalty
        with torch.no_grad():
            valid = [(w, m) for w, m in ((w_behaviour, behaviour_mask), (w_expert, expert_mask))]
            low = torch.stack([(w if m is None else torch.where(m, w, torch.full_like(w, math.inf))).min()
                               for w, m in valid])
            high = torch.stack([(w if m is None else torch.where(m, w, torch.zeros_like(w))).max() for w, m in valid])
            ess_weights = w_behaviour if behaviour_mask is None else torch.where(
                behaviour_mask, w_behaviour, torch.zeros_like(w_behaviour))
            diagnostics = {
                "density_ratio_behaviour_mean": behaviour_mean.detach(),
                "density_ratio_expert_mean": expert_mean.detach(),
                "density_ratio_min": low.min(),
                "density_ratio_max": high.max(),
                DENSITY_RATIO_ESS: effective_sample_size(ess_weights),
                "normalisation_penalty": penalty.detach(),
            }
        return loss, diagnostics

    def _validity_mask(self, samples: TensorDictBase, like: torch.Tensor) -> torch.Tensor | None:
        """TorchRL's validity mask of one set of samples (``("collector", "mask")`` and ``"shifted_valid"`` in the
        ``"behaviour"`` or ``"expert"`` sub-TensorDict, per ``loss_mask_key``), of ``like``'s shape; ``None`` where
        the set holds none. Masked samples are dropped from every mean (TorchRL's ``_reduce_loss`` rule)."""
        mask = None
        for key in self._loss_mask_keys():
            value = samples.get(key, None)
            if value is not None:
                value = self._expand_loss_mask(value, like)
                mask = value if mask is None else mask & value
        return mask

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Computes ``"loss_density_ratio"`` and the detached diagnostics (see the class docstring)."""
        loss, diagnostics = self.density_ratio_loss(tensordict)
        return TensorDict({LOSS_DENSITY_RATIO: loss, **diagnostics}, batch_size=[])
