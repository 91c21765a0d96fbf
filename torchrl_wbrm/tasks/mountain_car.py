"""MountainCarContinuous-v0 (Section 5.2), on the batched torch-native env: returns over fresh episodes."""
from __future__ import annotations

from torchrl.data import Bounded

from torchrl_wbrm.data import mountain_car as mountain_car_data
from torchrl_wbrm.data.datasets import OfflineDatasets
from torchrl_wbrm.data.mountain_car import MountainCarDataConfig
from torchrl_wbrm.tasks.base import EvalDefaults, Evaluator, QDefaults, Task, TrainingDefaults, to_dataclass
from torchrl_wbrm.evaluation import evaluate_returns
from torchrl_wbrm.modules import ActionGrid
from torchrl_wbrm.policies import make_mountain_car_env

__all__ = ["MountainCarEvaluator", "MountainCarTask"]

GYM_ID = "MountainCarContinuous-v0"


class MountainCarTask(Task):
    """``env.kind=mountain_car``: data by ``env.mountain_car_data``; actions in [−1, 1]; γ 0.99 unless ``q.gamma``."""

    kind = "mountain_car"
    data_module = mountain_car_data
    #: The score is the undiscounted return 100·[goal] − 0.1·Σa². At γ = 0.99 the discounted optimum is the forceful
    #: policy (reaching in ~80 steps is worth 100·0.99^80 ≈ 45 against ≈ 9 for a gentle ~240-step push), which scores
    #: ≈ 93.5; only γ close to 1 makes saving energy pay, as the score does.
    default_gamma = 0.9999
    #: the shared defaults, but: the paper's MountainCar behaviour data are whole expert episodes with noise plus random
    #: episodes, so the actor clones D's actions as TD3+BC does (``q.bc_alpha`` 10) instead of S^e's; SiLU Q, 4,000
    #: steps evaluated every 1,000, and 100 episodes per evaluation (the figures: :doc:`/results/paper_tables`)
    TRAINING_DEFAULTS = TrainingDefaults(
        q=QDefaults(bc_alpha=10.0, expert_bc_alpha=0.0, activation="SiLU", steps=4000, eval_every=1000),
        eval=EvalDefaults(episodes=100, train_episodes=100))

    def __init__(self, env) -> None:
        super().__init__(env)
        self.data_config: MountainCarDataConfig = to_dataclass(MountainCarDataConfig, env.mountain_car_data)

    def validate(self) -> None:
        data = self.data_config
        for key in ("parallel_envs", "expert_transitions", "behaviour_transitions"):
            if not getattr(data, key) >= 1:
                raise ValueError(f"env.mountain_car_data.{key} must be >= 1, got {getattr(data, key)!r}.")
        if not 0 < data.ratio_fraction < 1:
            raise ValueError(f"env.mountain_car_data.ratio_fraction must lie in (0, 1), got {data.ratio_fraction!r}.")

    def make_datasets(self, *, seed: int, storage: str = "lazy", scratch_dir=None) -> OfflineDatasets:
        return mountain_car_data.make_mountain_car_datasets(self.data_config, seed=seed, storage=storage,
                                                            scratch_dir=scratch_dir)

    def expected_sizes(self) -> dict[str, int]:
        data = self.data_config
        return {"behaviour": data.behaviour_transitions, "expert_samples": data.expert_transitions}

    def action_spec(self) -> Bounded:
        return Bounded(-1.0, 1.0, (self._action_dim(),))

    def action_grid(self, num_bins: int) -> ActionGrid:
        return ActionGrid.from_env(make_mountain_car_env(), num_bins)

    def evaluator(self, eval_cfg) -> "MountainCarEvaluator":
        return MountainCarEvaluator()

    def return_quantity(self) -> tuple[float, int]:
        return 1.0, 1000  # the evaluator's evaluate_returns defaults: undiscounted, at most 1000 steps

    def minari_env_kwargs(self, behaviour) -> dict:
        return {"env": GYM_ID, "eval_env": GYM_ID}


class MountainCarEvaluator(Evaluator):
    """The mean undiscounted return over fresh episodes, one car per episode in one batched env (built on first use,
    one per episode count)."""

    def __init__(self) -> None:
        super().__init__()
        self.envs: dict[int, object] = {}

    def evaluate(self, policy, *, episodes: int, seed: int, q_value=None, device=None) -> dict:
        if episodes not in self.envs:
            self.envs[episodes] = make_mountain_car_env(batch_size=[episodes])
        res = evaluate_returns(self.envs[episodes], policy, episodes=episodes, seed=seed)
        return {"return": res.mean, "return_ci": res.half_width, "return_stderr": res.stderr}
