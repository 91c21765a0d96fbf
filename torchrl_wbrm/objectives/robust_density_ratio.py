"""Stage 1 of WBRM: the robust density-ratio loss (Basu's power divergence), Section 3 of the paper."""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import dispatch, TensorDictModule
from tensordict.utils import NestedKey
from torchrl.objectives.common import LossModule

from torchrl_wbrm.objectives._fast import FunctionalCall
from torchrl_wbrm.objectives._utils import (
    check_finite,
    check_input_dtype,
    check_input_width,
    check_not_empty,
    check_reduction,
    check_same_features,
    check_sign,
    get_entry,
    input_width,
    reduce_batch,
)

__all__ = ["RobustDensityRatioLoss", "basu_power_divergence", "power_divergence_integrands"]


def power_divergence_integrands(w: torch.Tensor, alpha: float | str) -> tuple[torch.Tensor, torch.Tensor]:
    r"""The two integrands ``(ψ(w), φ(w))`` of the Basu power-divergence density-ratio loss.

    ``R_α(w) = E_b[ψ(w)] − E_e[φ(w)]`` with, for ``α > 0``,

        ψ(w) = w^{1+α},    φ(w) = (1 + 1/α) · w^α,

    and for the KL limit ``α → 0`` (``alpha="kl"``, the unnormalised-KL / KLIEP form) ``ψ(w) = w``, ``φ(w) = log w``.
    They come from the Bregman divergence ``E_b[f(w*) − f(w) − f'(w)(w* − w)]`` with ``f(t) = (t^{1+α} − t)/α``
    (``f(t) = t log t − t`` for KL): ``ψ = f'(w)w − f(w)``, ``φ = f'(w)``, constants dropped (Sugiyama, Suzuki &
    Kanamori 2012, "Density-ratio matching under the Bregman divergence"). At ``α = ½``: ``ψ = w^{3/2}``,
    ``φ = 3 w^{1/2}`` (the paper's Section 3); at ``α = 1``: ``ψ = w²``, ``φ = 2w`` (uLSIF).
    """
    if alpha == "kl":
        return w, torch.log(w)
    return w.pow(1 + alpha), (1 + 1 / alpha) * w.pow(alpha)


def basu_power_divergence(
    w_behaviour: torch.Tensor,
    w_expert: torch.Tensor,
    *,
    alpha: float | str = 0.5,
    relative_beta: float = 0.0,
    non_negative_correction: float | None = None,
    reduction: str = "mean",
) -> torch.Tensor:
    r"""The empirical robust density-ratio loss of Section 3 ("Density Ratio Estimation for dP^e/dP^b").

    Paper (α = ½):  ``R̂_S(w) = (1/m) Σ_i w(X^b_i, A^b_i)^{3/2} − (3/m) Σ_i w(X^e_i, A^e_i)^{1/2}``.
    General α (:func:`power_divergence_integrands`):  ``R̂_α(w) = mean_b ψ(w) − mean_e φ(w)``, minimised in
    population by the true ratio ``w^e = dP^e/dP^b`` for every α.

    Relative ratio (RuLSIF, Yamada et al. 2013), ``relative_beta = β ∈ [0, 1)``: the denominator law becomes the
    mixture ``βP^e + (1 − β)P^b`` and the minimiser the relative ratio ``p_e / (βp_e + (1 − β)p_b) ≤ 1/β``:

        R̂_{α,β}(w) = β · mean_e ψ(w) + (1 − β) · mean_b ψ(w) − mean_e φ(w).

    Non-negative correction (Kato & Teshima 2021, D3RE, "Non-negative Bregman divergence minimization for deep
    direct density ratio estimation"), ``non_negative_correction = C`` with ``0 < C < 1/sup w^e``: the denominator
    term is split as ``E_den ψ = (E_den ψ − C · E_e ψ) + C · E_e ψ``. The bracket is non-negative in population
    (``p_den − C·p_e ≥ 0`` and ``ψ ≥ 0``) but a flexible network can drive its empirical value negative by growing
    w on expert samples ("train-loss hacking"). It is therefore replaced by its absolute value, the gradient-ascent
    form of D3RE/nnPU: where the bracket is ≥ 0 the loss equals ``R̂``; where it is < 0 the gradient pushes it
    back up. (No host sync: ``abs`` instead of a Python branch.)

        R̂_nn(w) = | mean_den ψ(w) − C · mean_e ψ(w) | + C · mean_e ψ(w) − mean_e φ(w).

    Args:
        w_behaviour (Tensor): ŵ on behaviour samples S^b, all entries > 0.
        w_expert (Tensor): ŵ on expert samples S^e, all entries > 0.

    Keyword Args:
        alpha (float or "kl"): the power α > 0, or ``"kl"`` for the α → 0 limit. Defaults to ``0.5``.
        relative_beta (float): β of the relative ratio; ``0`` (default) is the plain ratio.
        non_negative_correction (float, optional): D3RE's C; ``None`` (default) means off.
        reduction (str): how samples are aggregated: ``"mean"`` (default), ``"sum"``, or ``"none"`` for per-pair
            terms (requires equal shapes and no correction).

    Examples:
        >>> import torch
        >>> w = torch.full((4,), 4.0)
        >>> basu_power_divergence(w, w, alpha=0.5)  # 4^{3/2} − 3·4^{1/2} = 8 − 6
        tensor(2.)
    """
    if reduction == "none" and non_negative_correction is not None:
        raise ValueError("The non-negative correction acts on batch means; it has no per-sample form.")
    reduce = functools.partial(reduce_batch, reduction=reduction)
    psi_behaviour, _ = power_divergence_integrands(w_behaviour, alpha)
    psi_expert, phi_expert = power_divergence_integrands(w_expert, alpha)
    denominator = (1 - relative_beta) * reduce(psi_behaviour) + relative_beta * reduce(psi_expert)
    if non_negative_correction is None:
        return denominator - reduce(phi_expert)
    corrected = non_negative_correction * reduce(psi_expert)
    return (denominator - corrected).abs() + corrected - reduce(phi_expert)


class RobustDensityRatioLoss(LossModule):
    r"""Fits ŵ(x, a) ≈ w^e = dP^{π^e}/dP^{π^b} by Basu's power divergence (Section 3, "Density Ratio Estimation").

    Paper (α = ½):  ``R̂_S(w) = mean_{S^b} w^{3/2} − 3 · mean_{S^e} w^{1/2}``; for any α > 0
    ``mean_b w^{1+α} − (1 + 1/α) · mean_e w^α`` (α = 1 is uLSIF) and the KL limit ``mean_b w − mean_e log w``
    (``alpha="kl"``). The equation lives in :func:`basu_power_divergence`. Its population minimiser is the true
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

        behaviour: NestedKey = "behaviour"
        expert: NestedKey = "expert"
        density_ratio: NestedKey = "density_ratio"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    out_keys = [
        "loss_density_ratio",
        "density_ratio_behaviour_mean",
        "density_ratio_expert_mean",
        "density_ratio_min",
        "density_ratio_max",
        "density_ratio_ess",
        "normalisation_penalty",
    ]

    ratio_network: TensorDictModule
    ratio_network_params: TensorDictParams
    target_ratio_network_params: TensorDictParams
    #: Call a plain ratio network on tensors (:mod:`torchrl_wbrm.objectives._fast`) instead of through a TensorDict
    #: and ``to_module``; the same computation (tested). ``False`` on an instance forces the TensorDict path.
    fast_path: bool = True

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

    def _fast(self) -> FunctionalCall | None:
        """The tensor call of the ratio network, or ``None`` where it needs the TensorDict path."""
        cache = self.__dict__.get("_fast_cache")
        if cache is None or cache[0] is not self.ratio_network or cache[2] != self.fast_path:
            call = None
            if self.fast_path and list(self.ratio_network.out_keys) == [self.tensor_keys.density_ratio]:
                call = FunctionalCall.build(self.ratio_network, self.ratio_network_params)
            cache = self.__dict__["_fast_cache"] = (self.ratio_network, call, self.fast_path)
        return cache[1]

    def _network_facts(self) -> tuple[int | None, torch.dtype | None]:
        """``(input width, parameter dtype)`` of the ratio network (cached per network)."""
        cache = self.__dict__.get("_facts_cache")
        if cache is None or cache[0] is not self.ratio_network:
            floats = [p for p in self.ratio_network_params.values(True, True) if p.is_floating_point()]
            cache = (self.ratio_network, input_width(self.ratio_network), floats[0].dtype if floats else None)
            self.__dict__["_facts_cache"] = cache
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
        for k, t in named.items():
            check_finite(t, k)
        fast = self._fast()
        if fast is not None:
            w = fast(self.ratio_network_params, *tensors)
        else:
            inputs = TensorDict(dict(zip(self.ratio_network.in_keys, tensors)), batch_size=samples.batch_size,
                                device=samples.device)
            with self.ratio_network_params.to_module(self.ratio_network, preserve_module_state=False):
                outputs = self.ratio_network(inputs)
            w = get_entry(outputs, key, f"the ratio network's output; its out_keys are {self.ratio_network.out_keys}")
        if w.shape not in (samples.batch_size, (*samples.batch_size, 1)):
            raise ValueError(
                f"The ratio network wrote {key!r} with shape {tuple(w.shape)} on {name!r} samples of batch size "
                f"{tuple(samples.batch_size)}; expected {tuple(samples.batch_size)} or {(*samples.batch_size, 1)}."
            )
        check_sign(w, key, strictly_positive=True)
        return w.reshape(samples.batch_size)

    def density_ratio_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The loss of Section 3 (:func:`basu_power_divergence`) plus options; returns ``(loss, diagnostics)``."""
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
        loss = basu_power_divergence(
            w_behaviour,
            w_expert,
            alpha=self.alpha,
            relative_beta=self.relative_beta,
            non_negative_correction=self.non_negative_correction,
            reduction=self.reduction,
        )
        denominator_mean = (1 - self.relative_beta) * w_behaviour.mean() + self.relative_beta * w_expert.mean()
        penalty = (denominator_mean - 1).pow(2)
        if self.normalisation_coefficient > 0:
            loss = loss + self.normalisation_coefficient * penalty
        with torch.no_grad():
            both = torch.cat([w_behaviour.reshape(-1), w_expert.reshape(-1)])
            diagnostics = {
                "density_ratio_behaviour_mean": w_behaviour.mean(),
                "density_ratio_expert_mean": w_expert.mean(),
                "density_ratio_min": both.min(),
                "density_ratio_max": both.max(),
                "density_ratio_ess": w_behaviour.sum().pow(2) / w_behaviour.pow(2).sum(),
                "normalisation_penalty": penalty.detach(),
            }
        return loss, diagnostics

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Computes ``"loss_density_ratio"`` and the detached diagnostics (see the class docstring)."""
        loss, diagnostics = self.density_ratio_loss(tensordict)
        return TensorDict({"loss_density_ratio": loss, **diagnostics}, batch_size=[])
