r"""The equations of WBRM's losses, each implemented once, on tensors (as :mod:`torchrl.objectives.value.functional`).

Every loss of :mod:`torchrl_wbrm.objectives` and every algorithm of :mod:`torchrl_wbrm.algos` computes these
quantities by calling the functions below, and nothing else computes them:

- stage 1, the density ratio: :func:`power_divergence_integrands`, :func:`basu_power_divergence` and the
  normalisation penalty :func:`normalisation_penalty`;
- stage 2, the Bellman residual: :func:`bellman_target`, :func:`bellman_residual`, :func:`weighted_bellman_residual`
  (its two forms), MABO's :func:`average_bellman_residual` and its linear adversary's closed form
  :func:`linear_adversary_weight`;
- the actor: :func:`td3bc_lambda`, TD3+BC's normalisation of the Q term, and :func:`action_cloning`, its cloning
  term (plain, or weighted and self-normalised over the batch);
- Q's blow-up bound: :func:`q_value_bound`, the largest |Q| a discounted return of bounded rewards reaches;
- the episodes' own returns that ``q.select=expert_like_return`` holds Q against: :func:`bootstrapped_returns`;
- the per-sample weight: :func:`per_sample_weight` (reading ŵ and the priority weight), :func:`reduce_batch`,
  :func:`weighted_reduce` and Kish's :func:`effective_sample_size` (the weights' diagnostics of the losses, of the
  stored ŵ and of the evaluation).
"""
from __future__ import annotations

import functools

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives.utils import _reduce

from torchrl_wbrm.objectives._utils import check_sign, checks_run, get_entry, per_sample

__all__ = [
    "RESIDUALS",
    "action_cloning",
    "average_bellman_residual",
    "basu_power_divergence",
    "bellman_residual",
    "bellman_target",
    "bootstrapped_returns",
    "effective_sample_size",
    "linear_adversary_weight",
    "normalisation_penalty",
    "per_sample_weight",
    "power_divergence_integrands",
    "q_value_bound",
    "reduce_batch",
    "relative_density_ratio",
    "return_residual",
    "masked_reduce",
    "td3bc_lambda",
    "weighted_bellman_residual",
    "weighted_mean_squared_residual",
    "weighted_reduce",
]

#: The forms of :func:`weighted_bellman_residual`.
RESIDUALS = ("squared", "absolute_mean")


# ---------------------------------------------------------------------- reductions and weights
def reduce_batch(value: torch.Tensor, reduction: str) -> torch.Tensor:
    r"""Reduce per-sample terms over the batch: the mean or the sum over every element, or the terms unchanged.

    .. math::

        \text{mean}: \frac{1}{n} \sum_i \ell_i, \qquad \text{sum}: \sum_i \ell_i, \qquad \text{none}: \ell_i

    Args:
        value (Tensor): the per-sample terms ``ℓ_i``.
        reduction (str): ``"mean"``, ``"sum"`` or ``"none"``.

    Examples:
        >>> import torch
        >>> reduce_batch(torch.tensor([1.0, 2.0, 6.0]), "mean")
        tensor(3.)
    """
    if reduction == "mean":
        return value.mean()
    if reduction == "sum":
        return value.sum()
    return value


def masked_reduce(value: torch.Tensor, reduction: str, mask: torch.Tensor | None = None) -> torch.Tensor:
    r""":func:`reduce_batch` over the samples where the bool ``mask`` (of ``value``'s shape) holds: TorchRL's rule
    for validity masks (``LossModule._reduce_loss``); the masked samples are selected away, not multiplied by 0 (a
    NaN there stays out).

    .. math::

        \text{mean}: \frac{\sum_i m_i \ell_i}{\max(1, \sum_i m_i)}, \qquad \text{sum}: \sum_i m_i \ell_i,
        \qquad \text{none}: m_i \ell_i

    Examples:
        >>> import torch
        >>> masked_reduce(torch.tensor([1.0, 5.0, float("nan")]), "mean", torch.tensor([True, True, False]))
        tensor(3.)
    """
    if mask is None:
        return reduce_batch(value, reduction)
    value = torch.where(mask, value, torch.zeros_like(value))
    if reduction == "mean":
        return value.sum() / mask.sum().clamp_min(1)
    return reduce_batch(value, reduction)


def weighted_reduce(value: torch.Tensor, weight: torch.Tensor, reduction: str) -> torch.Tensor:
    r"""The weighted reduction of TorchRL's prioritized losses (``torchrl.objectives.utils._reduce``).

    .. math::

        \text{mean}: \frac{\sum_i w_i \ell_i}{\sum_i w_i}, \qquad \text{sum}: \sum_i w_i \ell_i,
        \qquad \text{none}: w_i \ell_i

    Args:
        value (Tensor): the per-sample terms ``ℓ_i``, shape ``[*B]``.
        weight (Tensor): ``w_i ≥ 0``, shape ``[*B]``.
        reduction (str): ``"mean"``, ``"sum"`` or ``"none"``.

    Examples:
        >>> import torch
        >>> weighted_reduce(torch.tensor([1.0, 4.0]), torch.tensor([3.0, 1.0]), "mean")  # (3 + 4) / 4
        tensor(1.7500)
    """
    return _reduce(value, reduction=reduction, weights=weight)


def effective_sample_size(weight: torch.Tensor) -> torch.Tensor:
    r"""Kish's effective sample size of a batch's weights.

    .. math::

        \text{ESS} = \frac{\left(\sum_i w_i\right)^2}{\sum_i w_i^2}

    Examples:
        >>> effective_sample_size(torch.tensor([1.0, 1.0, 0.0, 0.0]))
        tensor(2.)
    """
    return weight.sum().pow(2) / weight.pow(2).sum()


def _read_weight(tensordict: TensorDictBase, key: NestedKey, value: torch.Tensor, dtype: torch.dtype | None,
                 check: bool) -> torch.Tensor:
    weight = per_sample(value, tensordict.batch_size, key).detach()
    if weight.is_complex():
        raise TypeError(f"Entry {key!r} has dtype {weight.dtype}; expected real, non-negative weights.")
    if not weight.is_floating_point():  # integer (or bool) weights: counts, 0/1 selections
        weight = weight.to(dtype or torch.get_default_dtype())
    if checks_run(check, value):
        check_sign(weight, key, strictly_positive=False)
    return weight


def per_sample_weight(
    tensordict: TensorDictBase,
    weight_key: NestedKey | None,
    priority_key: NestedKey | None = None,
    *,
    dtype: torch.dtype | None = None,
    check_weight: bool = True,
    check_priority: bool = True,
    why: str = "the per-sample weight ŵ(x, a)",
) -> torch.Tensor | None:
    r"""The per-sample weight of a batch: ŵ times TorchRL's priority weight, shape ``[*B]``, detached.

    .. math::

        w_i = \hat w(x_i, a_i) \cdot p_i

    ``ŵ_i`` is read from ``weight_key`` (a missing entry is a KeyError that says ``why``; ``None``: no ŵ) and
    ``p_i`` from ``priority_key`` where the batch holds it (``None``: not read), each of shape ``[*B]`` or
    ``[*B, 1]``. Integer or bool entries are cast to ``dtype`` (default: torch's default dtype); complex ones are a
    TypeError. Each factor is checked finite and non-negative on CPU (:func:`~torchrl_wbrm.objectives._utils.
    check_sign`) where :func:`~torchrl_wbrm.objectives._utils.checks_run` allows it (not inside ``torch.compile``,
    nor on a tensor a functorch transform wraps); ``check_weight=False`` (``check_priority=False``) leaves ŵ's
    (``p_i``'s) check to the caller. Returns ``None`` where neither factor applies.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> batch = TensorDict({"density_ratio": torch.tensor([[2.0], [0.5]]),
        ...                     "priority_weight": torch.tensor([1.0, 4.0])}, [2])
        >>> per_sample_weight(batch, "density_ratio", "priority_weight")
        tensor([2., 2.])
    """
    weight = None
    if weight_key is not None:
        weight = _read_weight(tensordict, weight_key, get_entry(tensordict, weight_key, why), dtype, check_weight)
    if priority_key is not None and priority_key != weight_key:
        priority = tensordict.get(priority_key, None)
        if priority is not None:
            priority = _read_weight(tensordict, priority_key, priority, dtype, check_priority)
            weight = priority if weight is None else weight * priority.to(weight.dtype)
    return weight


# ---------------------------------------------------------------------- stage 1: the density ratio
def power_divergence_integrands(w: torch.Tensor, alpha: float | str) -> tuple[torch.Tensor, torch.Tensor]:
    r"""The two integrands ``(ψ(w), φ(w))`` of the Basu power-divergence density-ratio loss.

    ``R_α(w) = E_b[ψ(w)] − E_e[φ(w)]`` with, for ``α > 0``,

    .. math::

        \psi(w) = w^{1+\alpha}, \qquad \varphi(w) = \left(1 + \tfrac{1}{\alpha}\right) w^{\alpha},

    and for the KL limit ``α → 0`` (``alpha="kl"``, the unnormalised-KL / KLIEP form) ``ψ(w) = w``, ``φ(w) = log w``.
    They come from the Bregman divergence ``E_b[f(w*) − f(w) − f'(w)(w* − w)]`` with ``f(t) = (t^{1+α} − t)/α``
    (``f(t) = t log t − t`` for KL): ``ψ = f'(w)w − f(w)``, ``φ = f'(w)``, constants dropped (Sugiyama, Suzuki &
    Kanamori 2012, "Density-ratio matching under the Bregman divergence"). At ``α = ½``: ``ψ = w^{3/2}``,
    ``φ = 3 w^{1/2}`` (the paper's Section 3); at ``α = 1``: ``ψ = w²``, ``φ = 2w`` (uLSIF).

    Examples:
        >>> import torch
        >>> power_divergence_integrands(torch.tensor([4.0]), 0.5)  # (4^{3/2}, 3 · 4^{1/2})
        (tensor([8.]), tensor([6.]))
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
    behaviour_mask: torch.Tensor | None = None,
    expert_mask: torch.Tensor | None = None,
) -> torch.Tensor:
    r"""The empirical robust density-ratio loss of Section 3 ("Density Ratio Estimation for dP^e/dP^b").

    Paper (α = ½):

    .. math::

        \hat R_S(w) = \frac{1}{m} \sum_i w(X^b_i, A^b_i)^{3/2} - \frac{3}{m} \sum_i w(X^e_i, A^e_i)^{1/2}.

    General α (:func:`power_divergence_integrands`):  ``R̂_α(w) = mean_b ψ(w) − mean_e φ(w)``, minimised in
    population by the true ratio ``w^e = dP^e/dP^b`` for every α.

    Relative ratio (RuLSIF, Yamada et al. 2013), ``relative_beta = β ∈ [0, 1)``: the denominator law becomes the
    mixture ``βP^e + (1 − β)P^b`` and the minimiser the relative ratio ``p_e / (βp_e + (1 − β)p_b) ≤ 1/β``:

    .. math::

        \hat R_{\alpha,\beta}(w) = \beta \,\overline{\psi(w)}_e + (1 - \beta)\, \overline{\psi(w)}_b
        - \overline{\varphi(w)}_e.

    Non-negative correction (Kato & Teshima 2021, D3RE, "Non-negative Bregman divergence minimization for deep
    direct density ratio estimation"), ``non_negative_correction = C`` with ``0 < C < 1/sup w^e``: the denominator
    term is split as ``E_den ψ = (E_den ψ − C · E_e ψ) + C · E_e ψ``. The bracket is non-negative in population
    (``p_den − C·p_e ≥ 0`` and ``ψ ≥ 0``) but a flexible network can drive its empirical value negative by growing
    w on expert samples ("train-loss hacking"). It is therefore replaced by its absolute value, the gradient-ascent
    form of D3RE/nnPU: where the bracket is ≥ 0 the loss equals ``R̂``; where it is < 0 the gradient pushes it
    back up. (No host sync: ``abs`` instead of a Python branch.)

    .. math::

        \hat R_{nn}(w) = \left| \overline{\psi(w)}_{den} - C\, \overline{\psi(w)}_e \right|
        + C\, \overline{\psi(w)}_e - \overline{\varphi(w)}_e.

    Args:
        w_behaviour (Tensor): ŵ on behaviour samples S^b, all entries > 0.
        w_expert (Tensor): ŵ on expert samples S^e, all entries > 0.

    Keyword Args:
        alpha (float or "kl"): the power α > 0, or ``"kl"`` for the α → 0 limit. Defaults to ``0.5``.
        relative_beta (float): β of the relative ratio; ``0`` (default) is the plain ratio.
        non_negative_correction (float, optional): D3RE's C; ``None`` (default) means off.
        reduction (str): how samples are aggregated: ``"mean"`` (default), ``"sum"``, or ``"none"`` for per-pair
            terms (requires equal shapes and no correction).
        behaviour_mask, expert_mask (Tensor, optional): bool, of ``w_behaviour``'s (``w_expert``'s) shape: the
            samples where it is False are dropped, TorchRL's rule for validity masks (the means run over the valid
            samples; ``"none"`` gives 0 at the others). Defaults to ``None`` (every sample counts).

    Examples:
        >>> import torch
        >>> w = torch.full((4,), 4.0)
        >>> basu_power_divergence(w, w, alpha=0.5)  # 4^{3/2} − 3·4^{1/2} = 8 − 6
        tensor(2.)
    """
    if reduction == "none" and non_negative_correction is not None:
        raise ValueError("The non-negative correction acts on batch means; it has no per-sample form.")
    psi_behaviour, _ = power_divergence_integrands(w_behaviour, alpha)
    psi_expert, phi_expert = power_divergence_integrands(w_expert, alpha)
    behaviour = functools.partial(masked_reduce, reduction=reduction, mask=behaviour_mask)
    expert = functools.partial(masked_reduce, reduction=reduction, mask=expert_mask)
    denominator = (1 - relative_beta) * behaviour(psi_behaviour) + relative_beta * expert(psi_expert)
    if non_negative_correction is None:
        return denominator - expert(phi_expert)
    corrected = non_negative_correction * expert(psi_expert)
    return (denominator - corrected).abs() + corrected - expert(phi_expert)


# ---------------------------------------------------------------------- stage 2: the Bellman residual
def bellman_target(
    reward: torch.Tensor, next_value: torch.Tensor, terminated: torch.Tensor, gamma: float | torch.Tensor
) -> torch.Tensor:
    r"""The Bellman-optimality target of Section 3, with no bootstrap after a termination.

    .. math::

        Y_i = R_i + \gamma \,(1 - \text{terminated}_i) \max_{a'} Q(X'_i, a')

    ``next_value`` is ``max_{a'} Q(X'_i, a')`` (from a maximiser, :mod:`torchrl_wbrm.modules.maximisers`). The
    operations are those of TorchRL's ``td0_return_estimate``, so the target is the TD(0) estimator's to the bit.
    Truncation without termination bootstraps.

    Args:
        reward (Tensor): ``R_i``.
        next_value (Tensor): ``max_{a'} Q(X'_i, a')``, of ``reward``'s shape.
        terminated (Tensor): bool, of ``reward``'s shape.
        gamma (float or Tensor): the discount γ (a tensor of ``reward``'s shape for per-sample discounts).

    Examples:
        >>> import torch
        >>> bellman_target(torch.tensor([1.0, 1.0]), torch.tensor([10.0, 10.0]), torch.tensor([False, True]), 0.9)
        tensor([10.,  1.])
    """
    if not (next_value.shape == reward.shape == terminated.shape):
        raise ValueError(
            f"bellman_target needs reward, next_value and terminated of one shape, got {tuple(reward.shape)}, "
            f"{tuple(next_value.shape)} and {tuple(terminated.shape)}."
        )
    return reward + gamma * (~terminated).int() * next_value


def bellman_residual(q_value: torch.Tensor, target_value: torch.Tensor) -> torch.Tensor:
    r"""The Bellman residual (TD error) of each sample.

    .. math::

        \delta_i = Q(X_i, A_i) - Y_i

    Examples:
        >>> import torch
        >>> bellman_residual(torch.tensor([1.0, 2.0]), torch.tensor([0.5, 3.0]))
        tensor([ 0.5000, -1.0000])
    """
    return q_value - target_value


def weighted_bellman_residual(
    q_value: torch.Tensor,
    target_value: torch.Tensor,
    weight: torch.Tensor,
    *,
    residual: str = "squared",
    reduction: str = "mean",
) -> torch.Tensor:
    r"""The weighted Bellman residual of Section 3 ("Methodology"), in its two forms.

    With ``δ_i = Q(X_i, A_i) − Y_i`` (:func:`bellman_residual`) and ``Y_i`` of :func:`bellman_target`:

    - ``"absolute_mean"`` (the paper's empirical loss):

      .. math::

          \hat L_{\hat w}(Q) = \left| \frac{1}{n} \sum_i \hat w(X_i, A_i)\, \delta_i \right|

      This is one equation per batch: on its own it pins Q only up to directions orthogonal to ŵ, so
      ``"squared"`` is the default (:doc:`/results/ablations`).
    - ``"squared"`` (no ½ factor):

      .. math::

          \frac{1}{n} \sum_i \hat w(X_i, A_i)\, \delta_i^2

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
    td_error = bellman_residual(q_value, target_value)
    if residual == "squared":
        return reduce_batch(weight * td_error.pow(2), reduction)
    if residual == "absolute_mean":
        weighted = reduce_batch(weight * td_error, reduction)
        return weighted if reduction == "none" else weighted.abs()
    raise ValueError(f"residual must be one of {RESIDUALS}, got {residual!r}.")


def average_bellman_residual(
    q_value: torch.Tensor,
    target_value: torch.Tensor,
    weight: torch.Tensor,
    *,
    reduction: str = "mean",
) -> torch.Tensor:
    r"""MABO's inner objective for one adversary ``w`` (Xie & Jiang 2020).

    .. math::

        \left| \frac{1}{n} \sum_i w(x_i, a_i)\, \delta_i \right|, \qquad \delta_i = Q(x_i, a_i) - Y_i

    For ``"mean"`` and ``"sum"`` this is :func:`weighted_bellman_residual` with ``residual="absolute_mean"``
    (called, not copied). ``"none"`` differs from that function on purpose: it returns the per-sample terms
    ``s · w_i δ_i`` with ``s = sign(Σ_j w_j δ_j)`` (detached), so that their mean (sum) equals the ``"mean"``
    (``"sum"``) loss *in value and in gradient* (``s`` is the sub-gradient of ``|·|``).

    Examples:
        >>> import torch
        >>> q, y, w = torch.tensor([1.0, 2.0]), torch.tensor([0.0, 4.0]), torch.tensor([1.0, 1.0])
        >>> average_bellman_residual(q, y, w)  # |(1 − 2) / 2|
        tensor(0.5000)
        >>> average_bellman_residual(q, y, w, reduction="none")  # sign(−1) · (1, −2)
        tensor([-1.,  2.])
    """
    if reduction == "none":
        signed = weighted_bellman_residual(q_value, target_value, weight, residual="absolute_mean", reduction="none")
        return signed * signed.sum().sign().detach()
    return weighted_bellman_residual(q_value, target_value, weight, residual="absolute_mean", reduction=reduction)


# ---------------------------------------------------------------------- the actor
def td3bc_lambda(alpha: float, q_value: torch.Tensor) -> torch.Tensor:
    r"""TD3+BC's weight of the Q term in the actor loss (Fujimoto & Gu 2021), detached.

    .. math::

        \lambda = \frac{\alpha}{\frac{1}{n} \sum_i |Q(x_i, \mu(x_i))|}

    The denominator is clamped at ``1e-6``. The actor loss is then ``λ · (−Q(x_i, μ(x_i))) + (cloning term)``, so
    the Q term has the same size whatever the reward scale.

    Args:
        alpha (float): α (2.5 in TD3+BC).
        q_value (Tensor): ``Q(x_i, μ(x_i))`` over the batch (any shape; a 0-dim tensor is its own mean).

    Examples:
        >>> import torch
        >>> td3bc_lambda(2.5, torch.tensor([-1.0, 3.0]))  # 2.5 / 2
        tensor(1.2500)
    """
    return alpha / q_value.abs().mean().detach().clamp_min(1e-6)


def action_cloning(mu: torch.Tensor, action: torch.Tensor, half_width: torch.Tensor,
                   weight: torch.Tensor | None = None) -> torch.Tensor:
    r"""The actor's cloning term in unit actions: the batch mean of ``‖(μ(x_b) − a_b) / h‖² / m``, or, with
    ``weight``, its mean self-normalised by the weights.

    .. math::

        \ell_b = \frac1m \left\lVert \frac{\mu(x_b) - a_b}{h} \right\rVert^2, \qquad
        \text{plain}: \frac1n \sum_b \ell_b, \qquad
        \text{weighted}: \frac{\sum_b w_b \ell_b}{\sum_b w_b}

    ``h`` is the half-width of the action box (the term has the same size whatever the action bounds) and ``m``
    the action dimension. The weights are detached (no gradient reaches them) and their sum is clamped at the
    dtype's smallest positive number: a batch whose weights are all 0 contributes 0. A row of weight 0 drops out;
    equal weights give the plain mean.

    Args:
        mu (Tensor): the actor's actions ``μ(x_b)``, shape ``[*B, m]``.
        action (Tensor): the actions cloned ``a_b``, shape ``[*B, m]``.
        half_width (Tensor): ``h``, shape ``[m]`` (or broadcastable).
        weight (Tensor, optional): ``w_b ≥ 0``, ``*B`` elements (``[*B]`` or ``[*B, 1]``); ``None``: the plain mean.

    Examples:
        >>> import torch
        >>> mu, a, h = torch.tensor([[1.0], [0.0]]), torch.tensor([[0.0], [0.0]]), torch.tensor([2.0])
        >>> action_cloning(mu, a, h)  # (0.25 + 0) / 2
        tensor(0.1250)
        >>> action_cloning(mu, a, h, torch.tensor([3.0, 1.0]))  # (3 · 0.25 + 1 · 0) / 4
        tensor(0.1875)
    """
    scaled = ((mu - action) / half_width).pow(2)
    if weight is None:
        return scaled.mean()
    per_row = scaled.mean(-1)
    weight = weight.detach().reshape(per_row.shape).to(per_row.dtype)
    return (weight * per_row).sum() / weight.sum().clamp_min(torch.finfo(per_row.dtype).tiny)


# ---------------------------------------------------------------------- Q's scale
def bootstrapped_returns(reward: torch.Tensor, target_value: torch.Tensor, episode: torch.Tensor,
                         gamma: float) -> torch.Tensor:
    r"""Each row's discounted return to the end of its episode, bootstrapped there by the row's Bellman target.

    .. math::

        G_t = r_t + \gamma G_{t+1} \ \text{inside an episode}, \qquad G_T = Y_T \ \text{at its last row}, \qquad
        \text{so} \quad G_t = \sum_{k=t}^{T-1} \gamma^{k-t} r_k + \gamma^{T-t} Y_T

    with ``Y = r + γ (1 − terminated) V(x')`` (:func:`bellman_target`): the (T − t + 1)-step Bellman target of row
    ``t``, the episode's observed rewards up to its end and Q's own value after it (0 where the episode terminated).
    ``Q(x_t, a_t) − G_t`` is the residual of the Bellman equation chained along the episode: a Q that has not carried
    a reward back along the episode, or has drifted away from the rewards, is far from it on every row before the
    reward, where the one-step residual is small on all rows but one. Computed by torchrl's
    :func:`~torchrl.objectives.value.functional.reward2go`.

    Args:
        reward (Tensor): ``r_t``, shape ``[N]``.
        target_value (Tensor): ``Y_t``, shape ``[N]``; only each episode's last row is read.
        episode (Tensor): the rows' episode ids, shape ``[N]``: each episode's rows contiguous and in time order.
        gamma (float): the discount.

    Examples:
        >>> import torch
        >>> r, y = torch.tensor([1.0, 1.0, 1.0, 2.0]), torch.tensor([0.0, 0.0, 5.0, 2.0])
        >>> bootstrapped_returns(r, y, torch.tensor([0, 0, 0, 1]), 0.5)  # 1 + 0.5 + 0.25 · 5, 1 + 0.5 · 5, 5; 2
        tensor([2.7500, 3.5000, 5.0000, 2.0000])
    """
    from torchrl.objectives.value.functional import reward2go

    episode = episode.reshape(-1)
    if not reward.shape == target_value.shape == episode.shape:
        raise ValueError(f"bootstrapped_returns needs reward, target_value and episode of one shape [N], got "
                         f"{tuple(reward.shape)}, {tuple(target_value.shape)} and {tuple(episode.shape)}.")
    last = torch.ones_like(episode, dtype=torch.bool)
    last[:-1] = episode[1:] != episode[:-1]
    chained = torch.where(last, target_value, reward)
    return reward2go(chained.unsqueeze(-1), last.unsqueeze(-1), gamma, time_dim=-2).squeeze(-1)


def q_value_bound(reward_max: float, gamma: float, factor: float = 1.0) -> float:
    r"""``factor`` times the largest discounted return of rewards bounded by ``reward_max``: Q past it has blown up.

    .. math::

        |Q(x, a)| \le \sum_{t \ge 0} \gamma^t \max|r| = \frac{\max|r|}{1 - \gamma}

    The trainer's one rule of Q's scale (:class:`~torchrl_wbrm.training.stops.QBound`: its warning during training and
    the results' ``q_blow_up`` flag) compares Q against this bound times one ``factor`` (a margin over the exact
    bound).

    Args:
        reward_max (float): max|r| over the data.
        gamma (float): the discount, below 1.
        factor (float): the margin over the bound. Defaults to 1.

    Examples:
        >>> q_value_bound(1.0, 0.9)
        10.000000000000002
        >>> q_value_bound(1.0, 0.9, factor=2.0)
        20.000000000000004
    """
    return factor * reward_max / (1.0 - gamma)


# ---------------------------------------------------------------------- what the trainer reads off a run
def relative_density_ratio(w: torch.Tensor, beta: float) -> torch.Tensor:
    r"""The relative density ratio of ``w = p_e / p_b``, for a mixture weight ``β`` (Yamada et al., 2013).

    .. math::

        w_\beta = \frac{p_e}{\beta p_e + (1 - \beta) p_b} = \frac{w}{\beta w + 1 - \beta} \le \frac{1}{\beta}

    ``β = 0`` is ``w`` itself. The trainer applies it to the exact ratio (``ratio.source=exact``) with
    ``ratio.relative_beta``, the ratio the robust loss then fits.

    Examples:
        >>> relative_density_ratio(torch.tensor([0.0, 1.0, 4.0]), 0.5)
        tensor([0.0000, 1.0000, 1.6000])
    """
    return w / (beta * w + 1 - beta)


def weighted_mean_squared_residual(squared_residual: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    r"""``mean ŵ δ²``: each row's squared Bellman residual ``δ²`` weighted by its stored ŵ, averaged over the rows.

    .. math::

        \frac{1}{N} \sum_i \hat w_i \, \delta_i^2

    The squared residual stage 2 minimises (:func:`weighted_bellman_residual`, ``reduction="mean"``), read on
    held-out episodes by ``q.select=held_out_weighted_residual``.

    Examples:
        >>> weighted_mean_squared_residual(torch.tensor([1.0, 4.0]), torch.tensor([2.0, 0.5]))
        tensor(2.)
    """
    return (weight.reshape(squared_residual.shape).to(squared_residual) * squared_residual).mean()


def return_residual(q_value: torch.Tensor, returns: torch.Tensor) -> torch.Tensor:
    r"""``mean (Q(x_t, a_t) − G_t)²``: Q against each row's own discounted return ``G_t``
    (:func:`bootstrapped_returns`), the figure of ``q.select=expert_like_return``.

    Examples:
        >>> return_residual(torch.tensor([1.0, 3.0]), torch.tensor([2.0, 1.0]))
        tensor(2.5000)
    """
    return (q_value.reshape(-1) - returns.reshape(-1)).pow(2).mean()


# ---------------------------------------------------------------------- stage 1's normalisation, MABO's adversary
def normalisation_penalty(behaviour_mean: torch.Tensor, expert_mean: torch.Tensor, relative_beta: float = 0.0
                          ) -> torch.Tensor:
    r"""The robust ratio loss's normalisation penalty: the squared gap of ŵ's mean under its denominator to 1.

    .. math::

        \left((1 - \beta)\, \mathbb{E}_b[\hat w] + \beta\, \mathbb{E}_e[\hat w] - 1\right)^2

    ``behaviour_mean`` and ``expert_mean``: ŵ's mean over the batch's behaviour and expert samples; ``β``: the
    relative ratio's mixture weight (0: the plain ratio, whose mean under the behaviour distribution is 1).
    :class:`~torchrl_wbrm.objectives.RobustDensityRatioLoss` adds it times ``normalisation_coefficient``.

    Examples:
        >>> normalisation_penalty(torch.tensor(1.5), torch.tensor(3.0))
        tensor(0.2500)
        >>> normalisation_penalty(torch.tensor(0.5), torch.tensor(1.5), relative_beta=0.5)
        tensor(0.)
    """
    return ((1 - relative_beta) * behaviour_mean + relative_beta * expert_mean - 1).pow(2)


def linear_adversary_weight(features: torch.Tensor, td_error: torch.Tensor, *, w_bound: float) -> torch.Tensor:
    r"""The closed-form inner max of MABO over the linear class ``W = {θᵀφ : ‖θ‖₂ ≤ B}``.

    With ``g = (1/n) Σ_i φ(x_i, a_i) δ_i``, ``|(1/n) Σ_i θᵀφ_i δ_i| = |θᵀg| ≤ B‖g‖₂`` (Cauchy–Schwarz), attained
    at ``θ* = B g / ‖g‖₂``. Returns the maximising weights ``w*_i = θ*ᵀφ_i`` (detached, shape ``[*B]``), so that
    ``(1/n) Σ_i w*_i δ_i = B‖g‖₂ = max_{w ∈ W} |(1/n) Σ_i w_i δ_i|``. Holding ``θ*`` fixed while differentiating
    w.r.t. Q gives the gradient of ``B‖g‖₂`` (Danskin's theorem). ``g = 0`` gives ``w* = 0``.

    Args:
        features (Tensor): ``φ(x_i, a_i)``, shape ``[*B, d]``.
        td_error (Tensor): ``δ_i``, shape ``[*B]`` (detached here).

    Keyword Args:
        w_bound (float): the radius ``B`` of the ball of θ.

    Examples:
        >>> phi = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
        >>> delta = torch.tensor([3.0, 4.0])  # g = (1.5, 2), ‖g‖ = 2.5
        >>> w = linear_adversary_weight(phi, delta, w_bound=2.0)  # θ* = 2 · (0.6, 0.8)
        >>> w, (w * delta).mean()  # B‖g‖ = 5
        (tensor([1.2000, 1.6000]), tensor(5.))
    """
    features, td_error = features.detach(), td_error.detach()
    num_features = features.shape[-1]
    g = (features * td_error.unsqueeze(-1)).reshape(-1, num_features).mean(0)
    theta = w_bound * g / g.norm().clamp_min(torch.finfo(g.dtype).tiny)
    return features @ theta
