"""The MABO baseline: Minimax Average Bellman Optimality (Xie & Jiang 2020)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torchrl.data import TensorSpec

from torchrl_wbrm.modules.maximisers import ActionMaximiser
from torchrl_wbrm.objectives._utils import per_sample
from torchrl_wbrm.objectives.functional import (average_bellman_residual, bellman_residual, linear_adversary_weight,
                                                 reduce_batch)
from torchrl_wbrm.objectives.weighted_bellman import WeightedBellmanLoss

__all__ = ["ADVERSARIES", "MABOLoss", "average_bellman_residual", "linear_adversary_weight"]

ADVERSARIES = ("network", "linear")


class MABOLoss(WeightedBellmanLoss):
    r"""MABO, Minimax Average Bellman Optimality (Xie & Jiang 2020), a baseline for offline ``Q*`` estimation.

        ``Q̂ = argmin_Q max_{w ∈ W} | E_b[ w(x, a) · (Q(x, a) − r − γ (1 − terminated) max_{a'} Q(x', a')) ] |``

    T. Xie and N. Jiang, "Q* approximation schemes for batch reinforcement learning: a theoretical comparison",
    UAI 2020 (the MABO estimator). ``E_b`` is the empirical mean over the batch of behaviour transitions; ``W`` is a
    class of bounded functions of ``(x, a)`` (the paper's analysis asks ``W`` to contain, approximately, the ratios
    ``d^π / μ`` of the relevant policies' state-action distributions to the data's, with ``‖w‖_∞ ≤ B``). With
    ``W = {ŵ}`` fixed this is the ``residual="absolute_mean"`` loss of
    :class:`~torchrl_wbrm.objectives.WeightedBellmanLoss`, which WBRM fits with a learned density ratio; MABO takes
    the worst case over ``W`` instead. Because ``w`` depends on ``(x, a)`` only, ``E[w δ] = E[w · E[δ | x, a]]``
    needs no double sampling: a rich ``W`` makes the inner max a norm of the Bellman *error*, not of the residual.

    No public implementation exists; the choices made here:

    - **The adversary class** (``adversary``):

      * ``"network"`` (default): ``w(x, a) = B · tanh(u(x, a))`` with ``u`` the raw output of ``critic_network``
        (one value per sample, under ``"adversary_output"``), so any network gives a class bounded in ``[−B, B]``
        and symmetric (negate ``u``'s last layer). The inner max is approximated by gradient *ascent*:
        ``"loss_critic" = −| mean_i w_i δ_i | + λ · mean_i w_i²`` (``λ = critic_l2``, default 0) is minimised w.r.t.
        the critic only. With ``λ > 0`` and a rich class the inner max becomes ``mean_i δ_i² / (4λ)`` (at
        ``w_i = ±δ_i / (2λ)`` inside the bound), a smooth squared Bellman error; this regularises the
        descent–ascent game, at the price of a bias towards small ``w``.
      * ``"linear"``: ``W = {θᵀφ(x, a) : ‖θ‖₂ ≤ B}`` with fixed features ``φ`` written by ``critic_network`` (shape
        ``[*B, d]``; e.g. a tabular indicator, polynomials or frozen random features). The inner max is exact,
        ``B · ‖mean_i φ_i δ_i‖₂`` (:func:`linear_adversary_weight`); there is no ``"loss_critic"`` and no critic
        optimiser. The feature module is evaluated under ``no_grad`` and is never trained by this loss.

    - **Each loss reaches only its own network.** ``"loss_value" = | mean_i w_i δ_i |`` with ``w`` detached trains Q
      (``"mean"``); ``"loss_critic"`` uses a detached ``δ`` and trains the adversary. Summing all ``loss_*`` entries
      and calling ``backward`` once is therefore simultaneous gradient descent–ascent; alternating updates (a critic
      step, then a Q step on a fresh forward) work too. The descent–ascent dynamics of the ``|·|`` game cycle
      without help: ``critic_l2 > 0`` and a critic learning rate above Q's damp them (``tests/test_mabo.py`` reaches
      Q* on a tabular chain MDP that way).
    - **Bootstrapping** (``delay_value``): ``False`` (default) is the paper's estimator, in which the same Q appears
      in ``Q(x, a)`` and ``max_{a'} Q(x', a')`` and the gradient flows through both. ``True`` evaluates the max with
      a frozen target copy of Q (updated outside the loss by :class:`~torchrl.objectives.SoftUpdate` /
      :class:`~torchrl.objectives.HardUpdate`), a fitted-Q-style variant. Truncation (``done`` without
      ``terminated``) bootstraps; termination does not.
    - **The max over next actions** reuses :class:`~torchrl_wbrm.objectives.WeightedBellmanLoss`'s machinery
      (this class subclasses it): a discrete Q head (greedy max), an ``actor_network`` μ (``Q(x', μ(x'))``, with
      ``"loss_actor" = −mean_i Q(x_i, μ(x_i))`` training μ only, optionally with TD3+BC's ``bc_alpha`` term) or
      ``maximiser="sampled"`` (the best of uniform candidates in ``action_spec``). See
      :mod:`torchrl_wbrm.modules.maximisers`.
    - γ is set with ``make_value_estimator(gamma=...)`` (TD(0) only); without it TorchRL's ``0.99`` applies.

    Args:
        value_network (TensorDictModule): Q, as for :class:`~torchrl_wbrm.objectives.WeightedBellmanLoss`:
            continuous actions write ``"state_action_value"`` ``[*B, 1]``; a discrete head writes
            ``"action_value"`` ``[*B, n]`` (data actions one-hot or indices).
        critic_network (TensorDictModule): the adversary class W. Reads its in_keys from the data (e.g.
            ``"observation"`` and ``"action"``; one-hot actions for a discrete problem) and writes
            ``"adversary_output"``: the raw ``u(x, a)``, shape ``[*B]`` or ``[*B, 1]``, for ``"network"``; the
            features ``φ(x, a)``, shape ``[*B, d]``, for ``"linear"``.

    Keyword Args:
        actor_network (TensorDictModule, optional): a deterministic actor μ writing ``"action"`` (continuous only).
        adversary (str): ``"network"`` (default) or ``"linear"``.
        w_bound (float): ``B > 0``, the bound of the class: ``|w| ≤ B`` (network) or ``‖θ‖₂ ≤ B`` (linear).
            Defaults to ``1.0``. It scales every loss by ``B``; take ``B`` at least as large as the density ratios
            W is meant to contain.
        critic_l2 (float): ``λ ≥ 0``, the L2 penalty ``λ · mean_i w_i²`` in ``"loss_critic"`` (network only).
            Defaults to ``0.0``.
        delay_value (bool): frozen target Q (``True``) or the paper's form with gradient through both Q terms
            (``False``, default).
        delay_actor (bool, optional): target copy of the actor for μ(x'). Defaults to ``delay_value``.
        maximiser (str or ActionMaximiser, optional): ``"discrete"``, ``"actor"``, ``"sampled"`` or an instance;
            defaults as in :class:`~torchrl_wbrm.objectives.WeightedBellmanLoss`.
        action_spec (Bounded, optional): action box for ``"sampled"``.
        num_action_samples (int): uniform candidates per state for ``"sampled"``. Defaults to ``64``.
        bc_alpha (float, optional): TD3+BC's α for ``"loss_actor"``. Defaults to ``None`` (no behaviour cloning).
        reduction (str, optional): ``"mean"`` (default, also for ``None``), ``"sum"`` or ``"none"``. ``"sum"`` is
            ``| Σ_i w_i δ_i |`` (and ``−| Σ_i w_i δ_i | + λ Σ_i w_i²``). ``"none"`` gives per-sample terms whose mean
            is the ``"mean"`` loss, value and gradient: ``s · w_i δ_i`` and ``−s · w_i δ_i + λ w_i²`` with
            ``s = sign(Σ_j w_j δ_j)`` (see :func:`~torchrl_wbrm.objectives.functional.average_bellman_residual`); ``"loss_actor"`` is ``−Q(x_i, μ(x_i))``.

    Output: ``"loss_value"``, ``"loss_critic"`` (``adversary="network"``), ``"loss_actor"`` (with an actor) and
    detached diagnostics ``"td_error_mean"``, ``"td_error_abs_mean"``, ``"q_mean"`` (mean Q(x, a)),
    ``"target_value_mean"``, ``"adversary_abs_mean"`` (mean ``|w_i|``), with an actor ``"actor_q_mean"`` (and
    ``"bc_loss"``). ``forward`` writes ``δ²`` (detached, ``[*B, 1]``) into the input under ``"td_error"`` as DQNLoss
    does; no other input entry is changed.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Bounded
        >>> from torchrl.modules import MLP, ValueOperator
        >>> from torchrl_wbrm.modules import make_deterministic_actor, make_q_network
        >>> from torchrl_wbrm.objectives import MABOLoss
        >>> spec = Bounded(-1.0, 1.0, (1,))
        >>> q = make_q_network(2, 1, initial_bias=0.0, num_cells=(32,))
        >>> actor = make_deterministic_actor(2, spec, num_cells=(32,))
        >>> adversary = ValueOperator(
        ...     MLP(in_features=3, out_features=1, num_cells=[32]),
        ...     in_keys=["observation", "action"], out_keys=["adversary_output"],
        ... )
        >>> loss = MABOLoss(q, adversary, actor_network=actor, w_bound=2.0)
        >>> loss.make_value_estimator(gamma=0.9)
        >>> n = 16
        >>> data = TensorDict({
        ...     "observation": torch.randn(n, 2),
        ...     "action": spec.rand((n,)),
        ...     ("next", "observation"): torch.randn(n, 2),
        ...     ("next", "reward"): torch.randn(n, 1),
        ...     ("next", "done"): torch.zeros(n, 1, dtype=torch.bool),
        ...     ("next", "terminated"): torch.zeros(n, 1, dtype=torch.bool),
        ... }, [n])
        >>> out = loss(data)
        >>> sorted(k for k in out.keys() if k.startswith("loss_"))
        ['loss_actor', 'loss_critic', 'loss_value']
        >>> bool(out["loss_critic"] == -out["loss_value"])  # no L2 penalty: the two players' objectives
        True
        >>> (out["loss_value"] + out["loss_critic"] + out["loss_actor"]).backward()  # descent–ascent step
        >>> # The linear class: the exact inner max B · ‖mean φ δ‖₂, no critic loss.
        >>> from tensordict.nn import TensorDictModule
        >>> features = TensorDictModule(lambda x, a: torch.cat([x, a, torch.ones_like(a)], -1),
        ...                             in_keys=["observation", "action"], out_keys=["adversary_output"])
        >>> linear = MABOLoss(q, features, actor_network=actor, adversary="linear")
        >>> sorted(k for k in linear(data).keys() if k.startswith("loss_"))
        ['loss_actor', 'loss_value']
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
            adversary (NestedKey): Where ``critic_network`` writes its output: the raw ``u(x, a)`` (``w = B·tanh u``)
                for ``adversary="network"``, the features ``φ(x, a)`` for ``adversary="linear"``.
                Defaults to ``"adversary_output"``.
            priority (NestedKey): The input tensordict key where δ² is written back. Defaults to ``"td_error"``.
            reward (NestedKey): The reward key, read under ``"next"``. Defaults to ``"reward"``.
            done (NestedKey): The done key, read under ``"next"``. Defaults to ``"done"``.
            terminated (NestedKey): The terminated key, read under ``"next"``; no bootstrap where it is True.
                Defaults to ``"terminated"``.
        """

        action: NestedKey = "action"
        state_action_value: NestedKey = "state_action_value"
        action_value: NestedKey = "action_value"
        adversary: NestedKey = "adversary_output"
        priority: NestedKey = "td_error"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys

    value_network: TensorDictModule
    value_network_params: TensorDictParams
    target_value_network_params: TensorDictParams
    actor_network: TensorDictModule
    actor_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams
    critic_network: TensorDictModule
    critic_network_params: TensorDictParams
    target_critic_network_params: TensorDictParams  # never created (no target adversary); declared for TorchRL

    def __init__(
        self,
        value_network: TensorDictModule,
        critic_network: TensorDictModule,
        *,
        actor_network: TensorDictModule | None = None,
        adversary: str = "network",
        w_bound: float = 1.0,
        critic_l2: float = 0.0,
        delay_value: bool = False,
        delay_actor: bool | None = None,
        maximiser: str | ActionMaximiser | None = None,
        action_spec: TensorSpec | None = None,
        num_action_samples: int = 64,
        bc_alpha: float | None = None,
        reduction: str | None = None,
    ) -> None:
        if adversary not in ADVERSARIES:
            raise ValueError(f"adversary must be one of {ADVERSARIES}, got {adversary!r}.")
        if not (isinstance(w_bound, (int, float)) and math.isfinite(w_bound) and w_bound > 0):
            raise ValueError(f"w_bound must be a finite number > 0, got {w_bound!r}.")
        if not (isinstance(critic_l2, (int, float)) and math.isfinite(critic_l2) and critic_l2 >= 0):
            raise ValueError(f"critic_l2 must be a finite number >= 0, got {critic_l2!r}.")
        if adversary == "linear" and critic_l2 != 0:
            raise ValueError(
                f"critic_l2={critic_l2!r} penalises a trained adversary; adversary='linear' has none (its inner max "
                "is exact). Use critic_l2=0 or adversary='network'."
            )
        super().__init__(
            value_network,
            actor_network=actor_network,
            residual="absolute_mean",  # recorded only: value_loss below replaces the base class's
            delay_value=delay_value,
            residual_gradient=not delay_value,  # the paper's form: the gradient through both Q terms
            delay_actor=delay_actor,
            use_weights=False,
            maximiser=maximiser,
            action_spec=action_spec,
            num_action_samples=num_action_samples,
            bc_alpha=bc_alpha,
            reduction=reduction,
        )
        self.adversary = adversary
        self.w_bound = float(w_bound)
        self.critic_l2 = float(critic_l2)
        self.convert_to_functional(critic_network, "critic_network", create_target_params=False)

    # ---------------------------------------------------------------- keys
    @property
    def in_keys(self) -> list[NestedKey]:
        if self._in_keys is None:
            keys = [*super().in_keys, *self.critic_network.in_keys]
            self._in_keys = list(dict.fromkeys(keys))
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values):
        self._in_keys = values

    @property
    def out_keys(self) -> list[str]:
        if self._out_keys is None:
            keys = list(super().out_keys)
            keys.insert(1, "adversary_abs_mean")
            if self.adversary == "network":
                keys.insert(1, "loss_critic")
            self._out_keys = keys
        return self._out_keys

    @out_keys.setter
    def out_keys(self, values):
        self._out_keys = values

    # ---------------------------------------------------------------- pieces
    def _out_key(self, name: str) -> NestedKey:
        return self.tensor_keys.adversary if name == "critic_network" else super()._out_key(name)

    def adversary_weight(self, tensordict: TensorDictBase, td_error: torch.Tensor) -> torch.Tensor:
        """The adversary's ``w(x_i, a_i)``, shape ``[*B]``.

        ``"network"``: ``B · tanh(u(x_i, a_i))``, differentiable w.r.t. the critic's parameters (``td_error`` unused).
        ``"linear"``: the exact maximiser of :func:`linear_adversary_weight` given ``td_error`` (detached).
        """
        key = self.tensor_keys.adversary
        batch = tensordict.batch_size
        inputs = self._entries(tensordict, self.critic_network.in_keys, "an input of the adversary (critic_network)")
        if self.adversary == "network":
            raw = self._call("critic_network", self.critic_network_params, inputs, batch)
            return self.w_bound * torch.tanh(per_sample(raw, batch, key))
        with torch.no_grad():
            features = self._call("critic_network", self.critic_network_params, inputs, batch)
        if features.ndim != len(batch) + 1 or features.shape[:-1] != batch:
            raise ValueError(
                f"Entry {key!r} has shape {tuple(features.shape)}; adversary='linear' expects features φ(x, a) of "
                f"shape {(*batch, 'd')}."
            )
        return linear_adversary_weight(features, td_error, w_bound=self.w_bound)

    def _losses(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor | None, dict]:
        """``(loss_value, loss_critic or None, diagnostics)`` from one evaluation of Q, its target and w."""
        q_value, target_value = self.bellman_error(tensordict)
        td_error = bellman_residual(q_value, target_value).detach()
        weight = self.adversary_weight(tensordict, td_error)
        loss_value = average_bellman_residual(q_value, target_value, weight.detach(), reduction=self.reduction)
        loss_critic = None
        if self.adversary == "network":
            loss_critic = -average_bellman_residual(
                q_value.detach(), target_value.detach(), weight, reduction=self.reduction
            )
            if self.critic_l2:
                loss_critic = loss_critic + self.critic_l2 * reduce_batch(weight.pow(2), self.reduction)
        with torch.no_grad():
            diagnostics = {
                "td_error": td_error.pow(2),
                "td_error_mean": td_error.mean(),
                "td_error_abs_mean": td_error.abs().mean(),
                "q_mean": q_value.mean(),
                "target_value_mean": target_value.mean(),
                "adversary_abs_mean": weight.abs().mean(),
            }
        return loss_value, loss_critic, diagnostics

    # ---------------------------------------------------------------- losses
    def value_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """``| mean_i w_i δ_i |`` with ``w`` fixed: trains Q only. Returns ``(loss, diagnostics)``.

        The diagnostics include the detached per-sample ``"td_error"`` (δ²), which :meth:`forward` writes back.
        """
        loss_value, _, diagnostics = self._losses(tensordict)
        return loss_value, diagnostics

    def critic_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """``−| mean_i w_i δ_i | + λ mean_i w_i²`` with ``δ`` fixed: trains the adversary only (``"network"``)."""
        if self.adversary != "network":
            raise ValueError("critic_loss needs adversary='network'; the linear adversary's inner max is exact.")
        _, loss_critic, diagnostics = self._losses(tensordict)
        return loss_critic, diagnostics

    def _value_terms(self, tensordict: TensorDictBase) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """``"loss_value"`` and, for the network adversary, ``"loss_critic"``: ``forward`` (inherited) adds the
        actor's loss and writes δ² into ``"td_error"``."""
        loss_value, loss_critic, diagnostics = self._losses(tensordict)
        losses = {"loss_value": loss_value}
        if loss_critic is not None:
            losses["loss_critic"] = loss_critic
        return losses, diagnostics
