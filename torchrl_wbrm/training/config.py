"""Structured (dataclass) Hydra configs of the recipes: a misspelt key or a bad type fails at start.

``register_configs()`` stores the schemas in Hydra's ``ConfigStore``; the YAML files under ``configs/`` name
them first in their defaults list, so every value they set is checked against the schema.

A run's config is prepared once, by :func:`prepare_config`, for one seed or many (``seeds``; each seed's run is
:meth:`PreparedConfig.for_seed`, not prepared again). Which check goes where:

* a key or a type: the schema (:func:`merge_config`: an unknown key is named with the nearest setting);
* a value of the run's settings (names from a fixed set, ranges, what two settings allow together):
  :func:`validate_config`, with the run as a whole (seeds, sizes, threads, the device, the logger, finite numbers)
  in :func:`~torchrl_wbrm.training.validation.validate_run_settings`;
* what the env allows: its task's hook, :meth:`~torchrl_wbrm.tasks.Task.check_config` (its data settings, its
  ground truth);
* what an algo allows: its registration (:class:`~torchrl_wbrm.algos.AlgoSpec`: ``validate`` for its
  ``baselines.<name>`` settings, the flags for the shared settings it reads);
* the data on disk, the run directory and a resume: before anything is written, by
  :meth:`~torchrl_wbrm.tasks.Task.check_data` and :func:`~torchrl_wbrm.training.resume.check_run_request`.
"""
from __future__ import annotations

import copy
import dataclasses
import functools
import math
from dataclasses import dataclass, field, make_dataclass
from typing import List, NamedTuple, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf

from torchrl_wbrm.algos import ALGOS, store_algo_configs
from torchrl_wbrm.tasks import EnvConfig, Task, get_task
from torchrl_wbrm.training.validation import validate_run_settings

__all__ = [
    "BaselinesConfig",
    "EvalConfig",
    "LoggerConfig",
    "MakeDatasetConfig",
    "PreparedConfig",
    "QConfig",
    "RatioConfig",
    "WBRMConfig",
    "config_as_dict",
    "config_schema",
    "env_config",
    "prepare_config",
    "register_configs",
    "resolve_defaults",
    "to_config",
    "validate_config",
]


@dataclass
class RatioConfig:
    """Stage 1: the density ratio ŵ ≈ dP^e/dP^b (Section 3, "Density Ratio Estimation").

    Attributes:
        source: ``"learned"`` (fit ŵ with the Basu loss), ``"exact"`` (the exact LQR ratio, a reference; not ``true``, which Hydra reads as a boolean) or
            ``"none"`` (w ≡ 1: the unweighted Bellman residual, the ablation).
        divergence: ``"basu"`` (power divergence with ``alpha``) or ``"kl"`` (its α → 0 limit).
        alpha: Basu's α (paper: 0.5; 1 is uLSIF).
        bounds: ``[Φ, Ψ]`` of Assumption 4.1, enforced by the network's output parameterisation.
        parameterisation: the bounded output map of :class:`~torchrl_wbrm.modules.DensityRatioNetwork`.
        num_cells: hidden widths (their number is the depth).
        activation: the hidden activation, the name of any :mod:`torch.nn` activation (``"ReLU"``, ``"SiLU"``, ...).
        layer_norm: a LayerNorm after each hidden layer.
        steps, batch_size, lr, weight_decay: the optimiser's budget (Adam).
        grad_clip: max gradient norm (``None``: off).
        holdout_fraction: share of S^b and S^e held out for early stopping.
        eval_every: steps between held-out evaluations; ``patience``: evaluations without improvement before
            stopping (the best held-out state is kept).
        normalisation_coefficient: weight of the penalty (mean_b ŵ − 1)².
        non_negative_correction: D3RE's C (``None``: off).
        relative_beta: β of the relative ratio p_e / (β p_e + (1 − β) p_b) (0: the plain ratio).
        self_normalise: divide the stored weights by their mean over D, so that they average 1.
        temper: λ in ŵ^λ (1: off). Default 0.25, the temper with the lowest held-out Bellman residual
            (:doc:`/results/weighting_study`).
        clip: upper clip of the stored weights (``None``: off).
        mix: ε in (1 − ε) ŵ + ε (0: off).
        aggregate: the weight each transition of D gets from ŵ: ``"transition"`` (ŵ at its own state-action) or
            ``"episode"`` (its episode's weight, the geometric mean of ŵ over the episode's transitions,
            :func:`~torchrl_wbrm.ratio.weights.episode_weights`; needs D's episode ids); then tempered, clipped,
            mixed and self-normalised as set above.
    """

    source: str = "learned"
    divergence: str = "basu"
    alpha: float = 0.5
    bounds: List[float] = field(default_factory=lambda: [1e-3, 1e3])
    parameterisation: str = "softplus"
    num_cells: List[int] = field(default_factory=lambda: [128, 128])
    activation: str = "ReLU"
    layer_norm: bool = False
    steps: int = 1500
    batch_size: int = 512
    lr: float = 1e-3
    weight_decay: float = 0.0
    grad_clip: Optional[float] = 10.0
    holdout_fraction: float = 0.1
    eval_every: int = 100
    patience: int = 5
    normalisation_coefficient: float = 0.0
    non_negative_correction: Optional[float] = None
    relative_beta: float = 0.0
    self_normalise: bool = True
    temper: float = 0.25
    clip: Optional[float] = None
    mix: float = 0.0
    aggregate: str = "transition"


@dataclass
class QConfig:
    """Stage 2: Q (and the actor) by the weighted Bellman residual (Section 3).

    Settings shown as "null: the env's" take the value of the env's task unless set (its typed
    :attr:`~torchrl_wbrm.tasks.Task.TRAINING_DEFAULTS`, a :class:`~torchrl_wbrm.tasks.TrainingDefaults`, applied by
    :func:`resolve_defaults`); the recipe and the Python API resolve them the same way.

    Attributes:
        residual: ``"squared"`` (mean ŵ δ²) or ``"absolute_mean"`` (the paper's |mean ŵ δ|).
        bootstrap: ``"target"`` (a frozen target network updated by SoftUpdate) or ``"residual_gradient"``
            (gradients through both Q terms).
        maximiser: ``"actor"`` (max ≈ Q(x', μ(x'))) or ``"sampled"`` (uniform candidates plus μ(x')).
        num_action_samples: candidates for ``"sampled"``.
        gamma: discount (null: the env's, :attr:`~torchrl_wbrm.tasks.Task.default_gamma`).
        num_cells, actor_num_cells: hidden widths of Q and of the actor (their number is the depth). Every algo's
            critics and actors use them.
        activation, actor_activation: hidden activations of Q (and of every critic/value network) and of the actor,
            the name of any :mod:`torch.nn` activation (Q's: null, the env's). Q's default is GELU, a smooth
            activation: the actor follows ∂Q/∂a, which a piecewise-linear ReLU network fits poorly; among smooth ones,
            the one with the lowest held-out Bellman residual (:doc:`/results/q_accuracy_study`).
        layer_norm, actor_layer_norm: a LayerNorm after each hidden layer of Q (and of every critic/value network)
            / of the actor. ``layer_norm`` null: the env's (:class:`~torchrl_wbrm.tasks.TrainingDefaults`).
        ensemble_size: independently initialised Q networks whose outputs are reduced by ``ensemble_reduction``
            (``"mean"`` or ``"min"``); the reduced value is Q everywhere (data term, target and actor).
        value_scale: Q = value_scale · MLP (reward/target scaling: the network works in units of value_scale).
        normalise_observations: feed every network ``(x − mean) / std`` of D's observations (a fixed input layer;
            null: the env's, on except for LQR, whose states are standardised already).
        lr_schedule: ``"cosine"`` (torch's ``CosineAnnealingLR`` over ``steps``, every optimiser; the default,
            :doc:`/results/q_accuracy_study`) or ``"constant"``.
        steps, batch_size, lr, actor_lr: the optimisers' budget (Adam; ``steps`` null: the env's).
        target_tau: SoftUpdate's τ.
        actor_delay: actor (and target) updates every this many critic steps (TD3's policy delay).
        weight_actor_loss: weight the actor's objective by ŵ too.
        bc_alpha: α of a TD3+BC behaviour-cloning term toward D's actions (null: the env's; 0: off).
        expert_bc_alpha: α of the actor's cloning of S^e's actions,
            ``λ·(−mean_D Q(x, μ(x))) + mean_{S^e} ‖(μ(x) − a)/h‖²/m``, λ = α / mean|Q| (``wbrm`` and ``brm`` with a
            continuous action; :class:`~torchrl_wbrm.algos.base.ExpertCloning`). Null: the env's; 0: off (the
            paper's actor). Setting one of ``bc_alpha`` and ``expert_bc_alpha`` turns the other off unless it is set
            too (both on is refused).
        expert_bc_weighted_d: that cloning term also clones the actor step's D batch weighted by each row's stored
            weight (``"density_ratio"``, shaped as the residual's), self-normalised over the batch. Needs
            ``expert_bc_alpha`` > 0; where there is no ŵ every weight is 1 (the plain cloning of D, the control).
        expert_bc_from_d: that cloning term's expert set is S^e with D's expert-like episodes
            (:func:`~torchrl_wbrm.ratio.expert_like_episodes`: the geometric mean of the raw ŵ over the episode,
            self-normalised over D, above 1). Needs ``expert_bc_alpha`` > 0 and D's episode ids; where there is no
            ŵ no episode is added.
        grad_clip: max gradient norm (``None``: off).
        holdout_fraction: share of D's episodes held out to score the Bellman residual on unseen behaviour data
            (a criterion a user without ground truth can compute).
        init_bias: start Q's output bias at mean(r) / (1 − γ) (otherwise the offset takes thousands of steps).
        eval_every: steps between evaluations (null: the env's).
        select: which stage-2 parameters the run delivers and scores at the end (null: the env's). ``"last"``:
            those of the last step. The others keep the evaluation (every ``eval_every`` steps, the last included)
            with the lowest figure, one selector each (:mod:`torchrl_wbrm.training.selection`):
            ``"held_out_residual"``, the unweighted Bellman residual on the held-out D episodes
            (``holdout_fraction``); ``"held_out_weighted_residual"``, the same with each row's δ² weighted by its ŵ
            as D's rows are; ``"expert_like_action"``, the actor's cloning error on D's expert-like episodes
            (:func:`~torchrl_wbrm.ratio.expert_like_episodes`); ``"expert_like_return"``, the mean of
            ``(Q(x_t, a_t) − G_t)²`` over their rows, ``G_t`` the episode's discounted return from ``t``
            bootstrapped at its end (:func:`~torchrl_wbrm.objectives.functional.bootstrapped_returns`; rows in time
            order). Both expert-like choices need D's episode ids, and where ŵ calls no episode expert-like they
            select by ``held_out_weighted_residual`` (``results.json``'s ``"selection"`` names the figure used).
            Needs an algo with a Bellman residual (wbrm, brm, fqi, mabo). The final record names the step chosen
            (``"selected_step"``); a resume with a larger ``steps`` continues from the last step's parameters
            (:doc:`/results/selection`).
    """

    residual: str = "squared"
    bootstrap: str = "target"
    maximiser: str = "actor"
    num_action_samples: int = 64
    gamma: Optional[float] = None
    num_cells: List[int] = field(default_factory=lambda: [256, 256])
    actor_num_cells: List[int] = field(default_factory=lambda: [256, 256])
    activation: Optional[str] = None
    actor_activation: str = "ReLU"
    layer_norm: Optional[bool] = None
    actor_layer_norm: bool = False
    ensemble_size: int = 1
    ensemble_reduction: str = "mean"
    value_scale: float = 1.0
    normalise_observations: Optional[bool] = None
    lr_schedule: str = "cosine"
    steps: Optional[int] = None
    batch_size: int = 256
    lr: float = 1e-3
    actor_lr: float = 1e-3
    target_tau: float = 0.05
    actor_delay: int = 2
    weight_actor_loss: bool = False
    bc_alpha: Optional[float] = None
    expert_bc_alpha: Optional[float] = None
    expert_bc_weighted_d: bool = False
    expert_bc_from_d: bool = False
    grad_clip: Optional[float] = None
    init_bias: bool = True
    holdout_fraction: float = 0.1
    eval_every: Optional[int] = None
    select: Optional[str] = None


@dataclass
class EvalConfig:
    """Evaluation, always on fresh episodes with its own seeds.

    Attributes:
        episodes: final evaluation episodes (null: the env's; LQR 1000 parallel episodes for the paired regret,
            100 elsewhere).
        train_episodes: episodes of the periodic evaluations during training (null: the env's; LQR 500, MountainCar
            100, Minari 10).
        seed: evaluation seed (distinct from the data seed).
        q_samples: expert (and behaviour) state-actions for the Q* and ratio errors (LQR).
        offline_value: (off by default) after training, estimate the delivered policy's value from D alone, without
            the environment (:mod:`torchrl_wbrm.training.offline_value`: FQE on D's training episodes, and ŵ-weighted
            where stage 2 weighted them), the same quantity as the online ``return``; written to ``results.json`` as
            ``final.offline_value`` with its 95% bootstrap interval over D's episodes.
        offline_value_steps: FQE's gradient steps for each of those estimates. A discounted return over a few dozen
            steps (LQR's) is fitted at the default; an undiscounted return over hundreds of steps needs far more,
            which is why the estimate is opt-in, and its interval covers the start states only, not the fit's error
            (docs: results/offline_value).
        offline_value_weights: the weights of the ŵ-weighted estimate (``final.offline_value_weighted``):
            ``"stage2"`` (the default), the weights stage 2 gave D's rows (``ratio.temper``, ``ratio.clip``,
            ``ratio.aggregate``, ``ratio.mix`` applied); ``"ratio"``, ratio-weighted FQE: the fitted ŵ itself before
            any of that shaping, self-normalised over D's rows. Use ``"ratio"`` to value a policy close to the
            expert from behaviour data that cover much more than the expert visits (docs: results/misspecified_q).
            Only an algo that fits ŵ (``wbrm``, ``mabo``, ...) has a weighted estimate.
    """

    episodes: Optional[int] = None
    train_episodes: Optional[int] = None
    seed: int = 1_000_000
    q_samples: int = 10_000
    offline_value: bool = False
    offline_value_steps: int = 2000
    offline_value_weights: str = "stage2"


@dataclass
class LoggerConfig:
    """Logging through ``torchrl.record.loggers.get_logger``.

    Attributes:
        backend: ``"csv"`` (default), ``"wandb"`` or ``""`` (none).
        project: wandb project.
        mode: wandb mode, ``"offline"`` unless a user asks for ``"online"``.
        log_every: training steps between scalar logs.
        group: wandb group (``None``: the Hydra sweep's folder name in a multirun, else none); runs of one sweep
            or study share it.
    """

    backend: str = "csv"
    project: str = "torchrl_wbrm"
    mode: str = "offline"
    log_every: int = 50
    group: Optional[str] = None


def _baselines_config() -> type:
    """``BaselinesConfig``: one field ``<name>`` per registered algo with settings of its own (its dataclass), in
    registration order; built from :data:`torchrl_wbrm.algos.ALGOS` when this module is imported."""
    fields = [(spec.name, spec.config, field(default_factory=spec.config)) for spec in ALGOS.values()
              if spec.config is not None]
    cls = make_dataclass("BaselinesConfig", fields)
    cls.__module__ = __name__
    cls.__doc__ = (
        "Settings of the algorithms that have their own (``baselines.<name>``, one field per algo of "
        ":data:`torchrl_wbrm.algos.ALGOS` with a config dataclass); shared settings (networks, lr, steps, batch size, "
        "γ, target τ, actor delay) come from ``q``, so every method gets the same networks, data and budget."
    )
    return cls


BaselinesConfig = _baselines_config()


@dataclass
class WBRMConfig:
    """``recipes/wbrm_offline.py``: the two-stage offline recipe.

    Attributes:
        env: the environment and its data (group ``env``): an :class:`~torchrl_wbrm.tasks.EnvConfig`, or the name of an
            env config as on the recipe's command line (``"lqr_exp1"``, ``"mountain_car"``, ``"minari"``: :func:`env_config`).
        algo: a name of :data:`torchrl_wbrm.algos.ALGOS` (group ``algo``, one file per algorithm under
            ``torchrl_wbrm/algos/``): ``"wbrm"`` (the two stages), ``"brm"`` (stage 2 alone with w ≡ 1: the
            unweighted ablation; the same as ``wbrm`` with ``ratio.source=none``), ``"bc"`` (behaviour cloning of the
            expert's actions in S^e with torchrl's ``BCLoss``, a reference) or a baseline on D.
        ratio: stage 1. q: stage 2 (and the shared settings of every algo). baselines: per-baseline settings. eval: evaluation. logger: logging (group ``logger``).
        seed: seeds data, initialisation and sampling.
        seeds: several seeds of this config trained together in one process (``seeds=[0,1,2,3,4]``; ``None``: the
            one run of ``seed``). Each seed gets the data, initialisation, draws and evaluation of a separate run
            with that seed, in ``<run dir>/seed<s>``; ``wbrm``, ``brm`` and ``fqi`` are vectorised over the seeds
            (:mod:`torchrl_wbrm.training.seeds`), other algos train them one at a time. The run directory's
            ``results.json`` holds every seed's results and their mean and 95% CI. ``resume=<run dir>`` continues an
            interrupted multi-seed run: its finished seeds are kept, the others continue or run anew.
        device: torch device.
        threads: torch threads (default 1, as the recipe: sweeps run runs side by side; ``None``: torch's default).
        checkpoint_every: steps between checkpoints (0: only at the end of each stage).
        data_cache: a folder to keep collected datasets in, keyed by env config and seed (``None``: collect anew).
        resume: a run directory to resume from (``None``: a new run). Only the keys of
            :data:`~torchrl_wbrm.training.resume.CONTINUABLE_KEYS` (a larger ``q.steps``, ``q.eval_every``,
            ``checkpoint_every``, ``plots``, ``threads``, ``data_cache``) and the ``eval`` and ``logger`` settings may
            differ from the checkpoint's; any other change is refused, naming the key with its old and new value.
        overwrite: let a new run replace a run directory that already holds a checkpoint or results (refused
            otherwise).
        plots: write PNG plots.
        verbose: show the libraries' INFO logging (torchrl's storage lines and the like), silenced otherwise.
    """

    env: EnvConfig = field(default_factory=EnvConfig)
    algo: str = "wbrm"
    ratio: RatioConfig = field(default_factory=RatioConfig)
    q: QConfig = field(default_factory=QConfig)
    baselines: BaselinesConfig = field(default_factory=BaselinesConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    seed: int = 0
    seeds: Optional[List[int]] = None
    device: str = "cpu"
    threads: Optional[int] = 1
    checkpoint_every: int = 1000
    data_cache: Optional[str] = None
    resume: Optional[str] = None
    overwrite: bool = False
    plots: bool = True
    verbose: bool = False

    def __post_init__(self):
        if isinstance(self.env, str):  # a name of the recipe's env group, as ``env=lqr_exp1`` on its command line
            self.env = env_config(self.env)


def env_config(name: str) -> EnvConfig:
    """The :class:`~torchrl_wbrm.tasks.EnvConfig` that ``env=<name>`` selects in the recipe: ``configs/env/<name>.yaml``
    merged on the schema. ``WBRMConfig(env="lqr_exp1")`` calls it. The Minari datasets of ``env="minari"`` are
    mandatory in the recipe (``env.minari.expert=... env.minari.behaviour=...``); here they are left empty, to be set
    on the returned config (an empty one is refused when the run starts).

    >>> env_config("lqr_exp3").lqr.F
    [[0.7, 0.0], [0.0, 0.7]]
    >>> env_config("lqr_exp9")
    Traceback (most recent call last):
    ...
    ValueError: env='lqr_exp9' is not an env config; the env configs are: lqr_custom, lqr_exp1, ...
    """
    from omegaconf import OmegaConf

    from torchrl_wbrm.configs import CONFIG_DIR

    names = sorted(path.stem for path in (CONFIG_DIR / "env").glob("*.yaml"))
    if name not in names:
        raise ValueError(f"env={name!r} is not an env config; the env configs are: {', '.join(names)}")
    node = OmegaConf.load(CONFIG_DIR / "env" / f"{name}.yaml")
    if "minari" in node:
        for key in [k for k in ("expert", "behaviour") if OmegaConf.is_missing(node.minari, k)]:
            del node.minari[key]  # mandatory on the command line (``???``): the schema's empty value here
    return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(EnvConfig), node))


@dataclass
class MakeDatasetConfig:
    """``recipes/make_dataset.py``: collect an offline dataset and save it.

    Attributes:
        env: the environment and its data settings (group ``env``).
        seed: the data seed.
        out: output directory (relative paths are relative to the launch directory).
        storage: ``"lazy"`` (RAM) or ``"memmap"`` (disk) replay-buffer storage while collecting.
        format: ``"torchrl"`` (this project's verified memory-mapped sets, :meth:`OfflineDatasets.save`) or
            ``"minari"`` (two Minari datasets, ``<minari_namespace>/expert-v0`` and ``<minari_namespace>/behaviour-v0``,
            written under ``out``, which then is a Minari data path).
        minari_namespace: the Minari namespace of the two datasets (``None``: ``make_dataset/<env.name>_seed<seed>``,
            apart from ``torchrl_wbrm.data.minari_examples``' ``examples/<env>``).
        overwrite: replace the dataset already at ``out`` (``format=minari``: the two ids) instead of refusing it
            (checked before any collecting).
    """

    env: EnvConfig = field(default_factory=EnvConfig)
    seed: int = 0
    out: str = "datasets/${env.name}_seed${seed}"
    storage: str = "lazy"
    format: str = "torchrl"
    minari_namespace: Optional[str] = None
    overwrite: bool = False


#: the settings whose values come from a fixed set; ``algo``'s set is the registry's (:func:`_choices`)
_CHOICES = {
    "ratio.source": ("learned", "exact", "none"),
    "ratio.divergence": ("basu", "kl"),
    "ratio.aggregate": ("transition", "episode"),
    "q.residual": ("squared", "absolute_mean"),
    "q.bootstrap": ("target", "residual_gradient"),
    "q.maximiser": ("actor", "sampled"),
    "q.ensemble_reduction": ("mean", "min"),
    "q.lr_schedule": ("constant", "cosine"),
    "q.select": ("last", "held_out_residual", "held_out_weighted_residual", "expert_like_action",
                 "expert_like_return"),
    "eval.offline_value_weights": ("stage2", "ratio"),
    "logger.backend": ("csv", "wandb", ""),
    "logger.mode": ("offline", "online", "disabled"),
}


def _get(cfg, dotted: str):
    for part in dotted.split("."):
        cfg = getattr(cfg, part)
    return cfg


def _choices() -> dict[str, tuple]:
    """:data:`_CHOICES` with ``algo``'s choices read from the registry now (an algo registered later is valid)."""
    return {"algo": tuple(ALGOS), **_CHOICES}


def resolve_defaults(cfg, task: Task | None = None):
    """``cfg`` with every setting it leaves null (``None``) set from the env's task
    (:meth:`~torchrl_wbrm.tasks.Task.training_defaults`): γ, the support term, the input normalisation, Q's
    activation and LayerNorm, the step budget, the parameters delivered (``q.select``) and the evaluation sizes; for an
    algo without a Bellman residual (:attr:`~torchrl_wbrm.algos.AlgoSpec.bellman_residual`) the shared defaults of
    :attr:`~torchrl_wbrm.tasks.Task.BELLMAN_RESIDUAL_SETTINGS` instead of the task's, but the task's LayerNorm
    for one with :attr:`~torchrl_wbrm.algos.AlgoSpec.critic_layer_norm`. A copy; settings already given are kept as
    they are.

    The trainer resolves the config it is given this way, so ``WBRMTrainer(WBRMConfig(env=...))`` runs the same
    method as ``python recipes/wbrm_offline.py env=...``. ``task``: the env's task, when built already (else built
    here).
    """
    import copy

    from omegaconf import DictConfig

    cfg = cfg.copy() if isinstance(cfg, DictConfig) else copy.deepcopy(cfg)
    # the actor's support term: one of the two cloning terms. Setting one (> 0) leaves the other off, so the env's
    # default term applies only when neither is set.
    if cfg.q.bc_alpha and cfg.q.expert_bc_alpha is None:
        cfg.q.expert_bc_alpha = 0.0
    if cfg.q.expert_bc_alpha and cfg.q.bc_alpha is None:
        cfg.q.bc_alpha = 0.0
    defaults = (task if task is not None else get_task(cfg.env)).training_defaults()
    spec = ALGOS.get(cfg.algo)
    if spec is not None and not spec.bellman_residual:  # the shared defaults, as the algo's reference defines it
        kept = {"layer_norm"} if spec.critic_layer_norm else set()
        shared = {key: getattr(Task.TRAINING_DEFAULTS.q, key) for key in Task.BELLMAN_RESIDUAL_SETTINGS
                  if key not in kept}
        defaults = dataclasses.replace(defaults, q=dataclasses.replace(defaults.q, **shared))
    for section, name, value in defaults.items():
        node = getattr(cfg, section)
        if getattr(node, name) is None:
            setattr(node, name, value)
    return cfg


@functools.lru_cache(maxsize=None)
def config_schema() -> DictConfig:
    """The :class:`WBRMConfig` schema as an OmegaConf node, built once per process (its cost: :doc:`/contributing`;
    ``OmegaConf.merge`` copies it and never changes it)."""
    return OmegaConf.structured(WBRMConfig)


def _merged_node(cfg) -> DictConfig:
    """``cfg`` (a dataclass, a DictConfig or a dict) as a typed OmegaConf node of :class:`WBRMConfig`: a dataclass's
    values checked against its field types, any other mapping merged on the schema (so unknown keys fail)."""
    if isinstance(cfg, WBRMConfig):
        return OmegaConf.structured(cfg)
    return OmegaConf.merge(config_schema(), cfg)


def _unknown_keys(node, schema, prefix: str = ""):
    """Dotted keys of ``node`` (a dataclass, DictConfig or dict) that ``schema`` (the schema's node) lacks."""
    from dataclasses import fields, is_dataclass

    if is_dataclass(node) and not isinstance(node, type):
        names = {f.name for f in fields(node)}
        items = [(k, v) for k, v in vars(node).items() if not k.startswith("_")]
        items = [(k, v) for k, v in items if k in names] + [(k, v) for k, v in items if k not in names]
    elif isinstance(node, (dict, DictConfig)):
        items = list(node.items_ex(resolve=False) if isinstance(node, DictConfig) else node.items())
    else:
        return
    for key, value in items:
        if not isinstance(schema, DictConfig) or key not in schema:
            yield f"{prefix}{key}", (list(schema.keys()) if isinstance(schema, DictConfig) else [])
        elif isinstance(schema[key] if not OmegaConf.is_missing(schema, key) else None, DictConfig):
            yield from _unknown_keys(value, schema[key], f"{prefix}{key}.")


def check_known_keys(cfg) -> None:
    """Refuse a config holding a key the schema does not have, however it was added (Hydra's ``+q.step=1000``, an
    attribute set on a dataclass), naming it and the nearest setting: a misspelt key fails at start instead of being
    ignored."""
    import difflib

    for key, siblings in _unknown_keys(cfg, config_schema()):
        parent, _, name = key.rpartition(".")
        near = difflib.get_close_matches(name, [str(k) for k in siblings], n=1)
        hint = f" (did you mean {parent + '.' if parent else ''}{near[0]}?)" if near else ""
        raise ValueError(f"{key} is not a setting of this recipe{hint}; see torchrl_wbrm.training.config.WBRMConfig "
                         f"for every setting.")


def merge_config(cfg) -> WBRMConfig:
    """A ``WBRMConfig`` from a dataclass, a DictConfig or a dict, merged on the schema; a key the schema does not
    have is refused (:func:`check_known_keys`), however it was added."""
    check_known_keys(cfg)
    return OmegaConf.to_object(_merged_node(cfg))


def to_config(cfg, task: Task | None = None) -> WBRMConfig:
    """:func:`merge_config`, its null settings resolved (:func:`resolve_defaults`): the recipe and the Python API run
    one method. ``task``: the env's task, when built already."""
    return resolve_defaults(merge_config(cfg), task)


class PreparedConfig(NamedTuple):
    """A run's config merged on the schema, resolved and validated (:func:`prepare_config`), and its env's task (no
    data attached yet): what a run builds once and hands on."""

    config: WBRMConfig
    task: Task

    def for_seed(self, seed: int) -> "PreparedConfig":
        """The run of one ``seed`` of this config (``seed`` set, ``seeds`` null), validated already: every entry of
        ``seeds`` was checked with the config. A task holds one run's data, so the seed's task is built anew."""
        config = copy.deepcopy(self.config)
        config.seed, config.seeds = int(seed), None
        return PreparedConfig(config, get_task(config.env))


def prepare_config(cfg) -> PreparedConfig:
    """The one preparation of a run's config: merged on the schema (:func:`merge_config`), its env's task built,
    resolved with the task's defaults (:func:`resolve_defaults`) and validated (:func:`validate_config`)."""
    merged = merge_config(cfg)
    task = get_task(merged.env)
    config = resolve_defaults(merged, task)
    _check_resolved(config, task)
    return PreparedConfig(config, task)


def config_as_dict(cfg, task: Task | None = None) -> dict:
    """``cfg`` (a :class:`WBRMConfig` or a Hydra ``DictConfig`` of one) as the plain dict a run saves under
    ``"config"`` in its checkpoint and ``results.json``. ``seeds`` appears only when set (a multi-seed run's), so a
    one-seed run's config reads as those saved before the key existed. ``task``: the env's task, when built
    already."""
    out = OmegaConf.to_container(resolve_defaults(_merged_node(cfg), task), resolve=True)
    if out.get("seeds") is None:
        out.pop("seeds", None)
    return out


def validate_config(cfg, task: Task | None = None) -> None:
    """Check values a type cannot: names from a fixed set, ranges. Raises ``ValueError`` naming the setting.

    Settings left null are checked as :func:`resolve_defaults` fills them. ``task``: the env's task, when built
    already (else built here). A run does not call it: :func:`prepare_config` is a run's one validation entry."""
    task = task if task is not None else get_task(cfg.env)
    _check_resolved(resolve_defaults(cfg, task), task)


def _check_resolved(cfg: WBRMConfig, task: Task) -> None:
    """:func:`validate_config`'s checks of a config resolved already, with its env's task's and its algo's hooks."""
    for key, allowed in _choices().items():
        value = _get(cfg, key)
        if value not in allowed:
            raise ValueError(f"{key}={value!r} is not allowed: choose one of {list(allowed)}.")
    from torchrl_wbrm.modules import resolve_activation

    for key in ("q.activation", "q.actor_activation", "ratio.activation"):
        resolve_activation(_get(cfg, key), key=key)
    for key in ("q.num_cells", "q.actor_num_cells", "ratio.num_cells"):
        widths = list(_get(cfg, key))
        if not all(int(c) > 0 for c in widths):
            raise ValueError(f"{key} must hold positive widths, got {widths}.")
    if not cfg.q.ensemble_size >= 1:
        raise ValueError(f"q.ensemble_size must be >= 1, got {cfg.q.ensemble_size!r}.")
    if not (cfg.q.value_scale > 0 and math.isfinite(cfg.q.value_scale)):
        raise ValueError(f"q.value_scale must be finite and > 0, got {cfg.q.value_scale!r}.")
    positive = ["ratio.steps", "ratio.batch_size", "ratio.lr", "q.steps", "q.batch_size", "q.lr", "q.actor_lr",
                "eval.episodes", "eval.train_episodes", "eval.offline_value_steps", "q.eval_every", "ratio.eval_every", "q.actor_delay",
                "logger.log_every"]
    for key in positive:
        if not _get(cfg, key) > 0:
            raise ValueError(f"{key} must be > 0, got {_get(cfg, key)!r}.")
    if not 0.0 < cfg.q.holdout_fraction < 1.0:
        raise ValueError(f"q.holdout_fraction must lie in (0, 1), got {cfg.q.holdout_fraction}.")
    if not 0.0 < cfg.ratio.holdout_fraction < 1.0:
        raise ValueError(f"ratio.holdout_fraction must lie in (0, 1), got {cfg.ratio.holdout_fraction}.")
    if cfg.ratio.divergence == "basu" and not cfg.ratio.alpha > 0:
        raise ValueError(f"ratio.alpha must be > 0 (use ratio.divergence=kl for the limit), got {cfg.ratio.alpha}.")
    if len(cfg.ratio.bounds) != 2:
        raise ValueError(f"ratio.bounds must hold two numbers [Φ, Ψ] with 0 < Φ < 1 ≤ Ψ, got {list(cfg.ratio.bounds)}.")
    low, high = cfg.ratio.bounds
    if not 0 < low < 1 <= high:
        raise ValueError(f"ratio.bounds=[Φ, Ψ] needs 0 < Φ < 1 ≤ Ψ (Assumption 4.1), got {list(cfg.ratio.bounds)}.")
    if not 0 < cfg.ratio.temper <= 1:
        raise ValueError(f"ratio.temper (λ in ŵ^λ) must lie in (0, 1], got {cfg.ratio.temper}.")
    if not 0 <= cfg.ratio.mix <= 1:
        raise ValueError(f"ratio.mix must lie in [0, 1], got {cfg.ratio.mix}.")
    if cfg.ratio.clip is not None and not cfg.ratio.clip > 0:
        raise ValueError(f"ratio.clip must be > 0 or null, got {cfg.ratio.clip}.")
    if cfg.q.gamma is not None and not 0 < cfg.q.gamma < 1:
        raise ValueError(f"q.gamma must lie in (0, 1) or be null, got {cfg.q.gamma}.")
    for key in ("q.bc_alpha", "q.expert_bc_alpha"):
        value = _get(cfg, key)
        if value is not None and not (math.isfinite(value) and value >= 0):
            raise ValueError(f"{key} must be >= 0 (0: off) or null (the env's), got {value!r}.")
    if cfg.q.bc_alpha and cfg.q.expert_bc_alpha:
        raise ValueError(f"q.bc_alpha={cfg.q.bc_alpha} (cloning D's actions) and q.expert_bc_alpha="
                         f"{cfg.q.expert_bc_alpha} (cloning S^e's) are both on: set one of them to 0.")
    for key, what in (("q.expert_bc_weighted_d", "the ŵ-weighted cloning of D"),
                      ("q.expert_bc_from_d", "D's expert-like episodes")):
        if not _get(cfg, key):
            continue
        if not cfg.q.expert_bc_alpha:
            raise ValueError(f"{key}=true adds {what} to the actor's S^e cloning term, which is off "
                             f"(q.expert_bc_alpha={cfg.q.expert_bc_alpha}): set q.expert_bc_alpha > 0.")
        if not ALGOS[cfg.algo].clones_expert:
            cloning = [name for name, spec in ALGOS.items() if spec.clones_expert]
            raise ValueError(f"{key}=true configures the S^e cloning term of the actor of {' and '.join(cloning)}, "
                             f"not algo={cfg.algo}.")
    if not 0 < cfg.q.target_tau <= 1:
        raise ValueError(f"q.target_tau must lie in (0, 1], got {cfg.q.target_tau}.")
    for spec in ALGOS.values():  # every algo's own settings (a toy algo registered late may have none here)
        if spec.validate is not None and hasattr(cfg.baselines, spec.name):
            spec.validate(getattr(cfg.baselines, spec.name), f"baselines.{spec.name}")
    if cfg.seeds is not None:
        seeds = list(cfg.seeds)
        if not seeds or len(set(seeds)) != len(seeds) or not all(isinstance(s, int) and s >= 0 for s in seeds):
            raise ValueError(f"seeds must be a non-empty list of distinct seeds >= 0 (or null), got {seeds}.")
    validate_run_settings(cfg)  # seeds, sizes, threads, device, finite numbers
    task.check_config(cfg)  # the env's hook: its data settings and what its ground truth supports


#: what :func:`register_configs` last stored: the ConfigStore and the registered algos (name and spec object)
_stored: tuple | None = None


def register_configs() -> None:
    """Store the recipes' schemas and every registered algo's node of the ``algo`` group (``algo/<name>``: it sets
    ``algo`` and ``baselines.<name>``) in Hydra's ``ConfigStore``.

    Storing makes each node an OmegaConf node (its cost: :doc:`/contributing`), and a study composes a config per
    run; so the nodes are stored again only when the registered algos, or the store, changed since the last call."""
    global _stored
    cs = ConfigStore.instance()
    stored = (id(cs), tuple((name, id(spec)) for name, spec in ALGOS.items()))
    if stored == _stored and "base_wbrm_offline.yaml" in cs.repo and "base_make_dataset.yaml" in cs.repo:
        return
    cs.store(name="base_wbrm_offline", node=WBRMConfig)
    cs.store(name="base_make_dataset", node=MakeDatasetConfig)
    store_algo_configs(cs, BaselinesConfig)
    _stored = stored
