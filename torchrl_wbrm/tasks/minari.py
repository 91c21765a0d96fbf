"""Two local Minari datasets (expert and behaviour), evaluated on their own gymnasium env."""
from __future__ import annotations

from dataclasses import replace

import torch
from torchrl.data import Bounded

from torchrl_wbrm.data.datasets import OfflineDatasets
from torchrl_wbrm.data.minari_data import (
    MinariDataConfig,
    OneHotActions,
    check_minari_data,
    make_minari_datasets,
    make_minari_eval_env,
    minari_discrete_action,
)
from torchrl_wbrm.tasks.base import Evaluator, QDefaults, Task, TrainingDefaults, to_dataclass
from torchrl_wbrm.evaluation import evaluate_returns
from torchrl_wbrm.modules import ActionGrid

__all__ = ["MinariEvaluator", "MinariTask"]


class MinariTask(Task):
    """``env.kind=minari``: the datasets of ``env.minari`` (read from disk, never downloaded, not cached again;
    ``env.minari.expert_episodes`` of the expert dataset's episodes drawn by the run's seed, else all); the
    action box is the datasets' (a ``Discrete`` action: its one-hot [0, 1]^n); γ 0.99 unless ``q.gamma``."""

    kind = "minari"
    collects_data = False
    #: for a continuous (``Box``) action, the shared defaults but: a LayerNorm in every critic, three times the budget
    #: (9,000 steps, evaluated every 1,500) and the evaluation with the lowest ŵ-weighted Bellman residual on the
    #: held-out D episodes delivered (``q.select``; the LayerNorm and the selection apply to an algo that fits a Bellman
    #: residual, :attr:`~Task.BELLMAN_RESIDUAL_SETTINGS`, and the LayerNorm to DDPG's critic). The LayerNorm holds Q's
    #: held-out residual as the budget grows; the selection keeps early parameters when Q drifts later in the run, and a
    #: run whose delivered return fell is flagged ``return_fell`` (the figures: :doc:`/results/benchmark`,
    #: :doc:`/results/selection`).
    TRAINING_DEFAULTS = TrainingDefaults(q=QDefaults(layer_norm=True, steps=9000, eval_every=1500,
                                                     select="held_out_weighted_residual"))
    #: the ``q`` settings a ``Discrete`` action keeps at the shared defaults (no LayerNorm, 3,000 steps, the last step)
    CONTINUOUS_ONLY = ("layer_norm", "steps", "eval_every", "select")

    def __init__(self, env) -> None:
        super().__init__(env)
        self.data_config: MinariDataConfig = to_dataclass(MinariDataConfig, env.minari)
        self._discrete: bool | None = None  # the datasets' action is a Discrete (training_defaults)

    def training_defaults(self) -> TrainingDefaults:
        """:attr:`TRAINING_DEFAULTS`, with the shared defaults for :attr:`CONTINUOUS_ONLY` when the datasets' action
        is a ``Discrete`` (read from the expert dataset's metadata)."""
        defaults = super().training_defaults()
        if self._discrete is None:  # read once per task
            self._discrete = minari_discrete_action(self.data_config)
        if self._discrete:
            shared = Task.TRAINING_DEFAULTS.q
            defaults = replace(defaults, q=replace(defaults.q, **{key: getattr(shared, key) for key in self.CONTINUOUS_ONLY}))
        return defaults

    def validate(self) -> None:
        wanted = self.data_config.expert_episodes
        if wanted is not None and not (isinstance(wanted, int) and wanted >= 1):
            raise ValueError(f"env.minari.expert_episodes must be >= 1 (the expert episodes drawn by the seed) or null "
                             f"(all of them), got {wanted!r}.")

    def check_data(self) -> None:
        check_minari_data(self.data_config, keep=True)

    def make_datasets(self, *, seed: int, storage: str = "lazy", scratch_dir=None) -> OfflineDatasets:
        return make_minari_datasets(self.data_config, seed=seed, storage=storage, scratch_dir=scratch_dir)

    def action_spec(self) -> Bounded:
        meta = self.datasets.metadata
        return Bounded(torch.tensor(meta["action_low"]), torch.tensor(meta["action_high"]), (self._action_dim(),))

    def action_grid(self, num_bins: int) -> ActionGrid:
        if self.datasets.metadata.get("discrete_actions"):  # a Discrete(n) action: its n actions, not a grid
            return OneHotActions(self.datasets.metadata["discrete_actions"])
        return ActionGrid.from_env(make_minari_eval_env(self.datasets.metadata), num_bins)

    def evaluator(self, eval_cfg) -> "MinariEvaluator":
        return MinariEvaluator(self.datasets.metadata)

    def return_quantity(self) -> tuple[float, int]:
        """The evaluator's undiscounted return over the datasets' episode limit (needs the datasets attached)."""
        return 1.0, self.datasets.metadata.get("max_episode_steps") or 1000


class MinariEvaluator(Evaluator):
    """The mean undiscounted return over episodes of the datasets' gymnasium env, all at once in a vector env of as
    many copies (the policy acts on the whole batch; copy ``i`` reset with ``seed + i``, so the figures are those of
    the episodes run one by one with those seeds), beside the datasets' own mean episode returns; where the datasets record Minari's reference scores (``ref_min_score``: random actions,
    ``ref_max_score``: the expert), also D4RL's normalised score ``100 (R − ref_min) / (ref_max − ref_min)``. The env is built now, so a missing one fails before training."""

    def __init__(self, metadata: dict) -> None:
        super().__init__()
        self.metadata = metadata
        self.env = make_minari_eval_env(metadata)  # built now: a missing env fails before training
        self._batched: dict[int, object] = {}  # episodes -> the vector env of as many copies

    def batched_env(self, episodes: int):
        """The vector env of ``episodes`` copies, built once per size."""
        if episodes not in self._batched:
            self._batched[episodes] = make_minari_eval_env(self.metadata, num_envs=episodes)
        return self._batched[episodes]

    def evaluate(self, policy, *, episodes: int, seed: int, q_value=None, device=None) -> dict:
        meta = self.metadata
        env = self.env if episodes == 1 else self.batched_env(episodes)
        res = evaluate_returns(env, policy, episodes=episodes, seed=seed,
                               max_steps=meta.get("max_episode_steps") or 1000)
        out = {"return": res.mean, "return_ci": res.half_width, "return_stderr": res.stderr}
        for key in ("behaviour_mean_return", "expert_mean_return"):  # the datasets' own, beside it
            if meta.get(key) is not None:
                out[f"data_{key}"] = float(meta[key])
        low, high = meta.get("ref_min_score"), meta.get("ref_max_score")
        if low is not None and high is not None and high > low:  # D4RL's score: 0 random actions, 100 the expert
            # imported here: data.benchmark imports data.minari_examples, which then could not run as
            # `python -m torchrl_wbrm.data.minari_examples` without runpy's "found in sys.modules" warning
            from torchrl_wbrm.data.benchmark import normalised_score

            out["normalised_score"] = float(normalised_score(res.mean, low, high))
            out["normalised_score_ci"] = 100.0 * res.half_width / (high - low)
            if meta.get("behaviour_mean_return") is not None:
                out["data_behaviour_normalised_score"] = float(normalised_score(meta["behaviour_mean_return"], low,
                                                                                 high))
        return out
