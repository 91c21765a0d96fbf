"""IQL (I. Kostrikov, A. Nair and S. Levine, "Offline reinforcement learning with implicit Q-learning", ICLR 2022)."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import IndependentNormal, ProbabilisticActor
from torchrl.objectives import IQLLoss, SoftUpdate

from torchrl_wbrm.algos.base import (Algo, AlgoContext, actor_options, adam, check_positive, critic_options,
                                    descend_all, q_network, q_reader, scalars)
from torchrl_wbrm.algos.registry import register_algo
from torchrl_wbrm.modules import make_deterministic_actor, make_q_network
from torchrl_wbrm.modules.action_scaling import ActionScaling


@dataclass
class IQLConfig:
    """IQL with torchrl's ``IQLLoss`` (``baselines.iql``), in unit actions
    (:class:`~torchrl_wbrm.modules.action_scaling.ActionScaling`) with the paper's Gaussian policy.

    Q and V start with the output bias every critic of the project gets, mean(r) / (1 − γ) (``q.init_bias``; the
    paper and d3rlpy start at 0). Where D's episodes end early that start is far above the value of the rows that
    end them: ``q.init_bias=false`` is then the closer match to d3rlpy (:doc:`/results/peer_d3rlpy`).

    Attributes:
        expectile: the value's expectile τ, in (0, 1).
        temperature: the inverse temperature β of the advantage weights exp(β A), which TorchRL caps at 100 (the
            paper's and d3rlpy's cap).
        loss_function: the critics' loss.
        min_log_std, max_log_std: the clamp of the policy's state-independent log standard deviation (d3rlpy's
            −5 and 2).
        init_log_std: the log standard deviation's initial value (the paper's 0). d3rlpy parameterises it as
            ``min + (max − min) · sigmoid(p)`` with ``p`` starting at 0, so its σ starts at exp(−1.5).
        lr, actor_lr, target_tau: Adam's rates for Q and V, and for the actor, and SoftUpdate's τ (they replace
            ``q.lr``, ``q.actor_lr`` and ``q.target_tau`` for this algo). The rates default to the project's 1e-3,
            not the paper's 3e-4, which is set for 10⁶ updates. τ defaults to the paper's and d3rlpy's 0.005, not
            the project's 0.05: IQL chains its value targets (V ← expectile of the target Q ← r + γ V), and a fast
            target lets that chain inflate the advantages of D's random actions, which the actor then clones
            (:doc:`/results/peer_d3rlpy`).
        critic_first: step Q and V on the batch first, then the actor with the updated V (d3rlpy's order). Off: the
            three losses are computed on the batch and stepped at once (torchrl's sota-implementations).
        unit_action_input: Q reads the unit action ``(a − c) / h`` itself (d3rlpy's and the paper's units: D4RL's
            boxes are ``[−1, 1]ᵐ``). Off: Q reads the env's box action, as every critic of this project does (the same
            function class; only the first layer's input is rescaled).
    """

    expectile: float = 0.7
    temperature: float = 3.0
    loss_function: str = "l2"
    min_log_std: float = -5.0
    max_log_std: float = 2.0
    init_log_std: float = 0.0
    lr: float = 1e-3
    actor_lr: float = 1e-3
    target_tau: float = 0.005
    critic_first: bool = False
    unit_action_input: bool = False


def _check(settings: IQLConfig, key: str) -> None:
    check_positive(settings, key, "temperature", "lr", "actor_lr", "target_tau")
    if not 0 < settings.expectile < 1:
        raise ValueError(f"{key}.expectile must lie in (0, 1), got {settings.expectile}.")
    if not settings.min_log_std < settings.max_log_std:
        raise ValueError(f"{key}.min_log_std must be < {key}.max_log_std, got {settings.min_log_std} and "
                         f"{settings.max_log_std}.")


class StateIndependentScale(nn.Module):
    """``loc ↦ (loc, σ)`` with ``σ = exp(clamp(log σ, lo, hi))`` one learned parameter per action coordinate,
    whatever the state (IQL's policy head; the log std starts at 0)."""

    def __init__(self, action_dim: int, min_log_std: float, max_log_std: float, init_log_std: float = 0.0):
        super().__init__()
        self.log_std = nn.Parameter(torch.full((action_dim,), float(init_log_std)))
        self.min_log_std, self.max_log_std = min_log_std, max_log_std

    def forward(self, loc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        scale = self.log_std.clamp(self.min_log_std, self.max_log_std).exp()
        return loc, scale.expand_as(loc)


def make_iql_actor(ctx: AlgoContext, unit_spec, settings: IQLConfig) -> ProbabilisticActor:
    """IQL's policy: ``N(tanh(μ(x)), diag σ²)`` on unit actions, σ state-independent (Kostrikov et al.'s
    ``tanh_squash_distribution=False`` policy, d3rlpy's ``NormalPolicy`` with a std parameter). The deterministic
    action (evaluation) is the mean ``tanh(μ(x))`` in ``[−1, 1]ᵐ``. The mean network is the project's deterministic
    actor on the unit box (``q.actor_*`` options)."""
    mean = make_deterministic_actor(ctx.observation_dim, unit_spec, **actor_options(ctx)).module
    head = StateIndependentScale(unit_spec.shape[-1], settings.min_log_std, settings.max_log_std,
                                 settings.init_log_std)
    module = TensorDictModule(nn.Sequential(mean, head), in_keys=["observation"], out_keys=["loc", "scale"])
    return ProbabilisticActor(module, in_keys=["loc", "scale"], spec=unit_spec, distribution_class=IndependentNormal,
                              return_log_prob=False)


@register_algo("iql", config=IQLConfig, validate=_check, loss="torchrl `IQLLoss`, Gaussian actor, V network",
               reference="Kostrikov et al. 2022", loss_title="IQL: losses")
def build_iql(ctx: AlgoContext) -> Algo:
    """torchrl's ``IQLLoss`` on D: V by expectile regression on the target Q (the min of two), Q on r + γ V(x'),
    the Gaussian actor by advantage-weighted regression on the data's actions, weights exp(β A) capped at 100
    (evaluated by its mean); targets by ``SoftUpdate``. V is ``make_q_network`` on the observation alone, with Q's
    output bias. D's actions are rescaled once into ``[−1, 1]ᵐ`` (the paper's and d3rlpy's action units), the
    evaluated policy maps the actor's mean back to the env's box and Q̂ is read at rescaled actions.
    """
    ic = ctx.cfg.baselines.iql
    scaling = ActionScaling(ctx.action_spec)
    actor = make_iql_actor(ctx, scaling.unit_spec, ic).to(ctx.device)
    value = make_q_network(ctx.observation_dim, 0, **critic_options(ctx), in_keys=("observation",),
                           out_key="state_value").to(ctx.device)
    critic = q_network(ctx) if ic.unit_action_input else scaling.unit_q_network(q_network(ctx))
    loss = IQLLoss(actor, critic, value, loss_function=ic.loss_function, temperature=ic.temperature,
                   expectile=ic.expectile)
    loss.make_value_estimator(gamma=ctx.gamma)
    updater = SoftUpdate(loss, tau=ic.target_tau)
    optimisers = {"qvalue": adam(loss.qvalue_network_params.values(True, True), ic.lr),
                  "actor": adam(loss.actor_network_params.values(True, True), ic.actor_lr),
                  "value": adam(loss.value_network_params.values(True, True), ic.lr)}

    def step(batch: TensorDictBase, i: int) -> dict:
        if ic.critic_first:  # Q and V, then the actor's advantage weights with the updated V
            loss_qvalue, _ = loss.qvalue_loss(batch.clone(False))
            loss_value, _ = loss.value_loss(batch.clone(False))
            descend_all({"loss_qvalue": loss_qvalue, "loss_value": loss_value},
                        {k: optimisers[k] for k in ("qvalue", "value")})
            loss_actor, _ = loss.actor_loss(batch.clone(False))
            descend_all({"loss_actor": loss_actor}, {"actor": optimisers["actor"]})
            out = {"loss_actor": loss_actor, "loss_qvalue": loss_qvalue, "loss_value": loss_value}
        else:
            out = loss(batch)
            descend_all({k: out[k] for k in ("loss_actor", "loss_qvalue", "loss_value")}, optimisers)
        updater.step()
        return scalars(out)

    return Algo(loss=loss, optimisers=optimisers, step=step, policy=scaling.policy(actor),
                q_value=scaling.q_reader(q_reader(loss.qvalue_network, loss.qvalue_network_params[0])),
                map_data=scaling.scale_data)
