"""Behaviour cloning (a reference, not offline RL): of S^e, of S^e ∪ D, of S^e ∪ D weighted by the stage-1 ŵ, of
S^e and D's expert-like episodes as the stage-1 ŵ finds them, or of S^e and D's true expert episodes
(``baselines.bc.data``)."""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torchrl.objectives import BCLoss

from torchrl_wbrm.keys import DENSITY_RATIO, EPISODE, EXPERT_LIKE
from torchrl_wbrm.algos.base import Algo, AlgoContext, adam, descend, deterministic_actor
from torchrl_wbrm.algos.registry import register_algo
from torchrl_wbrm.objectives.functional import action_cloning

#: ``baselines.bc.data``: what is cloned
BC_DATA = ("expert", "union", "weighted", "expert_like", "oracle")
#: the settings that read the stage-1 ŵ (stage 1 runs for them)
READS_RATIO = ("weighted", "expert_like")


@dataclass
class BCConfig:
    """Behaviour cloning (``baselines.bc``).

    Attributes:
        data: what is cloned. ``"expert"`` (the default): S^e, the expert's state-actions. ``"union"``: S^e ∪ D, every
            row alike. ``"weighted"``: S^e ∪ D, each row of D weighted by its stored stage-1 weight ŵ
            (``"density_ratio"``, after ``ratio.temper``, ``ratio.clip``, ``ratio.aggregate`` and the
            self-normalisation, as ``wbrm`` gets it; stage 1 runs for it) and each row of S^e by 1, the loss
            self-normalised over the batch: importance-weighted cloning of the union, as ISW-BC (Li et al., NeurIPS
            2023) clones D ∪ S^e weighted by a ratio d^e/d^union. ``ratio.source=none`` makes every weight 1 (the
            ŵ ≡ 1 control, ``"union"``). ``"expert_like"``: S^e and D's expert-like episodes, every row alike: the
            episodes whose raw stage-1 ŵ, self-normalised over D, has a geometric mean above 1
            (:func:`~torchrl_wbrm.ratio.expert_like_episodes`, as ``q.expert_bc_from_d`` finds them; D needs episode
            ids). ``ratio.source=none`` finds none (the ŵ ≡ 1 control: ``"expert"``). ``"oracle"``: S^e and D's true
            expert episodes, an upper reference that needs data that say which episodes are the expert's (the
            benchmark's, metadata ``expert_episode_ids``).
    """

    data: str = "expert"


NO_EXPERT_IDS = ("baselines.bc.data=oracle clones D's true expert episodes, but the behaviour data do not say which "
                 "episodes are the expert's (the benchmark's datasets do): choose another baselines.bc.data.")


def _check(settings: BCConfig, key: str) -> None:
    if settings.data not in BC_DATA:
        raise ValueError(f"{key}.data={settings.data!r} is not allowed: choose one of {list(BC_DATA)}.")


def _fits_ratio(cfg) -> bool:
    return cfg.baselines.bc.data in READS_RATIO


def cloned_data(data: str, behaviour: TensorDictBase, expert: TensorDictBase, *,
                expert_episode_ids: list[int] | None = None, weight_key: str = DENSITY_RATIO) -> TensorDictBase:
    """The rows ``baselines.bc.data`` clones, beside S^e: ``expert`` S^e's ``"observation"`` and ``"action"``,
    ``behaviour`` D's (with its stored weights under ``weight_key`` and its ``"episode"`` ids). Returns S^e's rows
    after D's (``"union"``, ``"weighted"``), D's rows marked ``"expert_like"`` by the trainer (``"expert_like"``) or
    D's rows of the episodes ``expert_episode_ids`` (``"oracle"``), with ``weight_key`` D's stored weight
    (``"weighted"``) or 1 (S^e's rows, and every row of the other settings).

        >>> import torch
        >>> from tensordict import TensorDict
        >>> d = TensorDict({"observation": torch.zeros(4, 1), "action": torch.zeros(4, 1), "episode": torch.tensor(
        ...     [0, 0, 1, 1]), "density_ratio": torch.tensor([[2.0], [2.0], [0.1], [0.1]])}, [4])
        >>> e = TensorDict({"observation": torch.ones(1, 1), "action": torch.ones(1, 1)}, [1])
        >>> cloned_data("weighted", d, e)["density_ratio"].flatten().tolist()
        [2.0, 2.0, 0.10000000149011612, 0.10000000149011612, 1.0]
        >>> cloned_data("oracle", d, e, expert_episode_ids=[1])["density_ratio"].flatten().tolist()
        [1.0, 1.0, 1.0]
        >>> d["expert_like"] = torch.tensor([True, True, False, False])
        >>> cloned_data("expert_like", d, e)["density_ratio"].flatten().tolist()
        [1.0, 1.0, 1.0]
    """
    if data not in BC_DATA[1:]:
        raise ValueError(f"baselines.bc.data={data!r}: cloned_data makes the union of one of {list(BC_DATA[1:])}.")
    keys = ["observation", "action"]
    d = behaviour.select(*keys, weight_key)
    if data == "oracle":
        if expert_episode_ids is None:
            raise ValueError(NO_EXPERT_IDS)
        if EPISODE not in behaviour.keys():
            raise ValueError("baselines.bc.data=oracle needs D's episode ids (key 'episode'), which these data lack.")
        d = d[torch.isin(behaviour[EPISODE], torch.as_tensor(list(expert_episode_ids), dtype=torch.int64))]
    elif data == "expert_like":
        if EXPERT_LIKE not in behaviour.keys():
            raise ValueError("baselines.bc.data=expert_like clones the rows the trainer marks 'expert_like' after "
                             "stage 1; these data have no such key.")
        d = d[behaviour[EXPERT_LIKE].reshape(-1).bool()]
    weight = d[weight_key]
    if data != "weighted":
        d.set(weight_key, torch.ones_like(weight))
    e = expert.select(*keys)
    e.set(weight_key, torch.ones(e.shape[0], *weight.shape[1:], dtype=weight.dtype, device=weight.device))
    return torch.cat([d, e.to(d.device)], 0)


@register_algo("bc", config=BCConfig, validate=_check, fits_ratio=_fits_ratio, loss="torchrl `BCLoss` on S^e",
               reference="behaviour cloning of the expert", loss_title="behaviour cloning loss")
def build_bc(ctx: AlgoContext) -> Algo:
    """Behaviour cloning (L2) of what ``baselines.bc.data`` names (:class:`BCConfig`): a reference, not offline RL.
    Budget: ``q.steps``, ``q.actor_lr``, ``q.batch_size``.

    ``"expert"``, ``"union"`` and ``"oracle"`` minimise torchrl's ``BCLoss`` (the batch mean of (μ(x) − a)²) on their
    rows; ``"weighted"`` minimises the ŵ-weighted cloning term
    (:func:`~torchrl_wbrm.objectives.functional.action_cloning`, in units of the action box's half-width: the same
    fit up to a constant factor, which Adam ignores) with the same actor and optimiser.
    """
    settings = ctx.cfg.baselines.bc
    actor = deterministic_actor(ctx)
    with warnings.catch_warnings():  # torchrl's BCLoss lacks the annotation its convert_to_functional asks for
        warnings.filterwarnings("ignore", message="The name target_actor_network_params wasn't part of the annotations",
                                category=UserWarning)
        loss = BCLoss(actor, loss_function="l2")
    optimisers = {"actor": adam(loss.actor_network_params.values(True, True), ctx.cfg.q.actor_lr)}
    if settings.data == "expert":
        return Algo(loss=loss, optimisers=optimisers, step=_bc_step(loss, optimisers), policy=actor, data="expert")
    datasets = ctx.task.datasets
    true_expert = datasets.metadata.get("behaviour_expert_episode_ids")
    if settings.data == "oracle" and true_expert is None:  # refused before any training
        raise ValueError(NO_EXPERT_IDS)
    expert = datasets.expert_samples[:]

    def map_data(d: TensorDictBase) -> TensorDictBase:  # D's training rows, their weights stored: the cloned rows
        return cloned_data(settings.data, d, expert, expert_episode_ids=true_expert)

    step = _bc_step(loss, optimisers)
    if settings.data == "weighted":
        half_width = ((ctx.action_spec.space.high - ctx.action_spec.space.low) / 2).clamp_min(1e-6)
        half_width = half_width.to(device=ctx.device, dtype=torch.float32)

        def step(batch: TensorDictBase, i: int) -> dict:
            with loss.actor_network_params.to_module(actor):
                mu = actor(batch.select(*actor.in_keys))["action"]
            loss_bc = action_cloning(mu, batch["action"], half_width, batch[DENSITY_RATIO])
            descend(loss_bc, optimisers["actor"])
            return {"loss_bc": loss_bc.detach()}

    return Algo(loss=loss, optimisers=optimisers, step=step, policy=actor, map_data=map_data,
                uses_ratio=settings.data in READS_RATIO,
                marks_expert_like=settings.data == "expert_like")


def _bc_step(loss: BCLoss, optimisers: dict):
    def step(batch: TensorDictBase, i: int) -> dict:
        loss_bc = loss(batch)["loss_bc"]
        descend(loss_bc, optimisers["actor"])
        return {"loss_bc": loss_bc.detach()}

    return step
