"""What the trainer, the algos and the recipes need to know about an environment, in one object per env kind."""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field, fields, replace
from typing import Any, ClassVar

import torch
from torchrl.data import Bounded

from torchrl_wbrm.data.datasets import OfflineDatasets

from torchrl_wbrm.modules import ActionGrid

__all__ = ["EvalDefaults", "Evaluator", "QDefaults", "Task", "TrainingDefaults", "to_dataclass"]


@dataclass(frozen=True)
class QDefaults:
    """A task's values of the ``q`` settings a config leaves null (:class:`~torchrl_wbrm.training.config.QConfig`).

    The shared values: the actor clones S^e's actions beside maximising Q (``expert_bc_alpha`` 1, λ = α / mean|Q| as
    in TD3+BC, :class:`~torchrl_wbrm.algos.base.ExpertCloning`: a term that keeps μ on the data's support); networks
    see ``(x − mean) / std`` of D's observations (gymnasium observations differ in scale by orders of magnitude);
    GELU, no LayerNorm, 3,000 steps evaluated every 500, the last step's parameters delivered. ``gamma`` ``None``:
    the task's :attr:`Task.default_gamma`.
    """

    expert_bc_alpha: float = 1.0
    bc_alpha: float = 0.0
    normalise_observations: bool = True
    activation: str = "GELU"
    layer_norm: bool = False
    steps: int = 3000
    eval_every: int = 500
    select: str = "last"
    gamma: float | None = None


@dataclass(frozen=True)
class EvalDefaults:
    """A task's values of the ``eval`` settings a config leaves null
    (:class:`~torchrl_wbrm.training.config.EvalConfig`): 100 final episodes, 10 per periodic evaluation."""

    episodes: int = 100
    train_episodes: int = 10


@dataclass(frozen=True)
class TrainingDefaults:
    """A task's training defaults: the values its config's null settings take, one typed field per setting."""

    q: QDefaults = field(default_factory=QDefaults)
    eval: EvalDefaults = field(default_factory=EvalDefaults)

    def items(self):
        """``(section, name, value)`` for every setting, e.g. ``("q", "steps", 3000)``."""
        for section in fields(self):
            node = getattr(self, section.name)
            for f in fields(node):
                yield section.name, f.name, getattr(node, f.name)


def to_dataclass(cls, value):
    """``value`` as a ``cls``: the dataclass itself, or an OmegaConf/dict node of its fields."""
    if isinstance(value, cls):
        return value
    from omegaconf import DictConfig, OmegaConf

    if isinstance(value, DictConfig):
        value = OmegaConf.to_container(value, resolve=True)
    return cls(**value)


class Evaluator(ABC):
    """Scores a policy (and Q̂) on fresh episodes of one env.

    Attributes:
        eval_samples: name -> TensorDict of ``"observation"``, ``"action"`` where Q̂ is scored against the exact Q*
            (empty where Q* is unknown).
        true_ratio: the exact density ratio dP^e/dP^b as a TensorDictModule writing ``"density_ratio"``, or ``None``.
    """

    eval_samples: dict
    true_ratio: Any = None

    def __init__(self) -> None:
        self.eval_samples = {}

    @abstractmethod
    def evaluate(self, policy, *, episodes: int, seed: int, q_value=None, device=None) -> dict:
        """Flat dict of floats: ``return`` (with ``_ci``, ``_stderr``) and whatever else the env can score."""
        raise NotImplementedError


class Task(ABC):
    """One environment kind (``env.kind``): its data, its action box, γ, its evaluator and its ground truth.

    A task is made from the env config (:func:`~torchrl_wbrm.tasks.get_task`) before any data exist (to check
    the config and build the data); :meth:`attach` then gives it the datasets, which the action box, the action grid
    and the evaluator may read.
    """

    kind: ClassVar[str] = ""
    #: the exact density ratio dP^e/dP^b is known (``ratio.source=exact``)
    has_exact_ratio: ClassVar[bool] = False
    #: ``recipes/make_dataset.py`` can collect this env's data (``False``: its data are read, not collected)
    collects_data: ClassVar[bool] = True
    #: γ when ``q.gamma`` is null
    default_gamma: float = 0.99
    #: the values of the settings a config leaves null (``None``), applied by
    #: :func:`~torchrl_wbrm.training.config.resolve_defaults`, so the recipe and the Python API run the same method on
    #: every env. The shared defaults hold on every benchmark task with no per-task tuning; a subclass changes one only
    #: for a reason it documents (the figures: :doc:`/results/benchmark`).
    TRAINING_DEFAULTS: ClassVar[TrainingDefaults] = TrainingDefaults()

    #: the ``q`` settings whose task default applies to an algo that fits a Bellman residual only
    #: (:attr:`~torchrl_wbrm.algos.AlgoSpec.bellman_residual`: WBRM, BRM, FQI, MABO); every other algo (BC and the
    #: baselines TD3+BC, IQL, CQL, ...) gets the shared values, its critics as its reference defines them, but the
    #: task's LayerNorm goes to an algo with :attr:`~torchrl_wbrm.algos.AlgoSpec.critic_layer_norm` (DDPG).
    #: ``q.select`` scores evaluations by the held-out Bellman residual, which only those algos fit.
    BELLMAN_RESIDUAL_SETTINGS: ClassVar[tuple[str, ...]] = ("layer_norm", "select")

    def training_defaults(self) -> TrainingDefaults:
        """:attr:`TRAINING_DEFAULTS` with ``q.gamma`` (:attr:`default_gamma`): the values of the settings a config
        leaves null."""
        return replace(self.TRAINING_DEFAULTS, q=replace(self.TRAINING_DEFAULTS.q, gamma=self.default_gamma))

    def __init__(self, env) -> None:
        """``env``: the env config (:class:`~torchrl_wbrm.tasks.EnvConfig`, or an OmegaConf node of one)."""
        self.env = env
        self.datasets: OfflineDatasets | None = None
        #: the seconds :meth:`check_data` took where the run's checks called it (reading the data on disk before the
        #: run starts): counted in the run's ``data_seconds`` and ``wall_seconds``
        self.check_seconds = 0.0

    # ------------------------------------------------------------------ before any data
    def check_config(self, cfg) -> None:
        """The task's hook in a run's one validation (:func:`~torchrl_wbrm.training.config.prepare_config`): what this
        env allows of the run's config ``cfg`` (a resolved :class:`~torchrl_wbrm.training.config.WBRMConfig`), and
        its data settings (:meth:`validate`); ``ValueError`` naming the setting. By default: the exact ratio
        (``ratio.source=exact``) needs a task that knows it (:attr:`has_exact_ratio`)."""
        if cfg.ratio.source == "exact" and not self.has_exact_ratio:
            raise ValueError(f"ratio.source='exact' needs an env whose exact density ratio is known (LQR), got "
                             f"env.kind={self.kind!r}.")
        self.validate()

    def validate(self) -> None:
        """Check the env's data settings before any data are collected; ``ValueError`` naming the key."""

    def check_data(self) -> None:
        """Read and check the data on disk the config names, before a run writes anything (a one-line error naming
        the dataset, and for a bad value the episode, the step and the key); what was read is held for this
        process's next :meth:`make_datasets`, which then does not read it again. Data the task collects are not
        checked here. By default: a saved dataset named by the data config's ``dataset_dir``
        (:func:`~torchrl_wbrm.data.datasets.read_saved_dataset`)."""
        from torchrl_wbrm.data.datasets import read_saved_dataset

        directory = getattr(getattr(self, "data_config", None), "dataset_dir", None)
        if directory:
            read_saved_dataset(directory, keep=True)

    @abstractmethod
    def make_datasets(self, *, seed: int, storage: str = "lazy", scratch_dir=None) -> OfflineDatasets:
        """Collect (or read) the three sets ``D``, ``S^b``, ``S^e``."""
        raise NotImplementedError

    def expected_sizes(self) -> dict[str, int] | None:
        """The set sizes the config asks for (``{"behaviour": |D| + |S^b|, "expert_samples": |S^e|}``), which a data
        cache entry must hold; ``None``: the data are on disk already and are not cached."""
        return None

    # ------------------------------------------------------------------ with the data
    def attach(self, datasets: OfflineDatasets) -> "Task":
        self.datasets = datasets
        return self

    def _action_dim(self) -> int:
        return self.datasets.transitions[:]["action"].shape[-1]

    @abstractmethod
    def action_spec(self) -> Bounded:
        """The action box the actors are bounded to."""
        raise NotImplementedError

    def return_quantity(self) -> tuple[float, int] | None:
        """``(γ, H)``: the evaluator's online ``return`` is the γ-discounted return of an episode of at most H steps
        (γ = 1: undiscounted), the quantity an offline estimate must match; ``None`` where the task does not say.
        Known without building the evaluator (no environment): an offline estimate needs no env."""
        return None

    def gamma(self, override: float | None = None) -> float:
        """``override`` (``q.gamma``) or the env's own discount."""
        return override or self.default_gamma

    @abstractmethod
    def action_grid(self, num_bins: int) -> ActionGrid:
        """The env's discretised action box (``algo=dqn``)."""
        raise NotImplementedError

    @abstractmethod
    def evaluator(self, eval_cfg) -> Evaluator:
        """The evaluator (``eval_cfg``: :class:`~torchrl_wbrm.training.config.EvalConfig`'s fields)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ recipes/make_dataset.py format=minari
    #: the data module whose ``collect_transitions`` builds this env's sets (their collections are recorded)
    data_module: ClassVar[Any] = None

    def recorded_collections(self, *, seed: int, storage: str = "lazy"):
        """The datasets and the collections they are made from: ``(datasets, behaviour, expert)``, where
        ``behaviour`` and ``expert`` hold whole episodes (the behaviour part(s) are collected first, the expert last)."""
        module, calls = self.data_module, []
        original = module.collect_transitions

        def recording(*args, **kwargs):
            out = original(*args, **kwargs)
            calls.append(out)
            return out

        module.collect_transitions = recording
        try:
            datasets = self.make_datasets(seed=seed, storage=storage)
        finally:
            module.collect_transitions = original
        if len(calls) < 2:
            raise RuntimeError(f"Expected a behaviour and an expert collection, recorded {len(calls)}.")
        return datasets, torch.cat(calls[:-1], 0), calls[-1]

    def minari_env_kwargs(self, behaviour) -> dict:
        """What :func:`~torchrl_wbrm.data.write_minari_dataset` records of the env: a gymnasium id, or the spaces.
        Only the tasks whose data the project makes itself can be exported (``make_dataset format=minari``)."""
        raise NotImplementedError(f"{type(self).__name__} (env.kind={self.kind!r}) cannot be exported as a Minari "
                                  f"dataset: make_dataset format=minari writes the project's own envs.")
