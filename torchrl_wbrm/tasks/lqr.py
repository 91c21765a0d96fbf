"""The LQR systems (Section 5.1): exact ground truth (the optimum, Q*, the density ratio), paired regret."""
from __future__ import annotations

import math

from torchrl.data import Bounded

from torchrl_wbrm.data import lqr as lqr_data
from torchrl_wbrm.data.datasets import OfflineDatasets, collect_transitions, min_behaviour_episodes
from torchrl_wbrm.data.lqr import LQRDataConfig
from torchrl_wbrm.tasks.base import EvalDefaults, Evaluator, QDefaults, Task, TrainingDefaults, to_dataclass
from torchrl_wbrm.envs import LQRConfig, LQREnv, make_lqr_env
from torchrl_wbrm.evaluation import lqr_paired_regret, q_error
from torchrl_wbrm.modules import ActionGrid
from torchrl_wbrm.policies import lqr_true_density_ratio, make_lqr_behaviour, make_lqr_expert

__all__ = ["LQREvaluator", "LQRTask"]


class LQRTask(Task):
    """``env.kind=lqr``: any F, G, R (``env.lqr``), data by ``env.lqr_data``; γ is the system's (0.9)."""

    kind = "lqr"
    has_exact_ratio = True
    data_module = lqr_data

    def __init__(self, env) -> None:
        super().__init__(env)
        self.lqr_config: LQRConfig = to_dataclass(LQRConfig, env.lqr)
        self.data_config: LQRDataConfig = to_dataclass(LQRDataConfig, env.lqr_data)
        self._lqr_env: LQREnv | None = None

    @property
    def lqr_env(self) -> LQREnv:
        """The system itself, for its exact solution (``optimal_q``, ``riccati``, ...)."""
        if self._lqr_env is None:
            self._lqr_env = LQREnv(self.lqr_config)
        return self._lqr_env

    #: the shared defaults, but: the states are already standardised (x₀ ~ N(0, I)), so no input normalisation; the
    #: exact paired regret needs many parallel episodes (1000 final, 500 during training), which the batched env
    #: runs at once
    TRAINING_DEFAULTS = TrainingDefaults(q=QDefaults(normalise_observations=False),
                                         eval=EvalDefaults(episodes=1000, train_episodes=500))

    @property
    def default_gamma(self) -> float:
        return self.lqr_config.gamma

    def validate(self) -> None:
        data = self.data_config
        for key in ("parallel_envs", "expert_episodes"):
            if not getattr(data, key) >= 1:
                raise ValueError(f"env.lqr_data.{key} must be >= 1, got {getattr(data, key)!r}.")
        if not 0 < data.ratio_fraction < 1:
            raise ValueError(f"env.lqr_data.ratio_fraction must lie in (0, 1), got {data.ratio_fraction!r}.")
        needed = min_behaviour_episodes(data.ratio_fraction)
        if not data.dataset_dir and not data.behaviour_episodes >= needed:
            raise ValueError(f"env.lqr_data.behaviour_episodes must be >= {needed} (split by episode into S^b and D, "
                             f"and D again into training and held-out sets), got {data.behaviour_episodes!r}.")
        if not 0 <= data.expert_tau <= 1:
            raise ValueError(f"env.lqr_data.expert_tau must lie in [0, 1], got {data.expert_tau!r}.")
        if not data.behaviour_noise_std >= 0:
            raise ValueError(f"env.lqr_data.behaviour_noise_std must be >= 0, got {data.behaviour_noise_std!r}.")
        start = data.behaviour_initial_std
        if start is not None and not (isinstance(start, (int, float)) and math.isfinite(start) and start > 0):
            raise ValueError(f"env.lqr_data.behaviour_initial_std must be null (the system's initial_std) or a finite "
                             f"number > 0, got {start!r}.")
        lqr = self.lqr_config
        if lqr.reward_clip is not None:
            if lqr.reward_clip != 0:
                raise ValueError(
                    f"env.lqr.reward_clip={lqr.reward_clip!r}: the exact return (the evaluation's ground truth) is "
                    f"implemented for a clip at 0 (the paper's) or none (env.lqr.reward_clip=null)."
                )
            if lqr.state_dim > 2:
                raise ValueError(
                    f"env.lqr: a {lqr.state_dim}-dimensional state with the reward clipped at 0 is not supported: the "
                    f"exact clipped return (the evaluation's ground truth) is implemented for state dimension <= 2. "
                    f"Set env.lqr.reward_clip=null to train and score on the unclipped reward, whose exact return "
                    f"holds in any dimension."
                )

    def make_datasets(self, *, seed: int, storage: str = "lazy", scratch_dir=None) -> OfflineDatasets:
        data = self.data_config
        storage = data.storage if storage == "lazy" else storage  # env.lqr_data.storage=memmap: buffers on disk
        if data.dataset_dir:  # a saved dataset (e.g. a large one made once), verified on load
            return OfflineDatasets.load(data.dataset_dir, storage=storage, scratch_dir=scratch_dir)
        return lqr_data.make_lqr_datasets(self.lqr_config, data, seed=seed, storage=storage, scratch_dir=scratch_dir)

    def expected_sizes(self) -> dict[str, int]:
        data, horizon = self.data_config, self.lqr_config.horizon
        return {"behaviour": data.behaviour_episodes * horizon, "expert_samples": data.expert_episodes * horizon}

    def action_spec(self) -> Bounded:
        bound = self.lqr_config.action_bound
        return Bounded(-bound, bound, (self._action_dim(),))

    def action_grid(self, num_bins: int) -> ActionGrid:
        return ActionGrid.from_lqr_env(self.lqr_config, num_bins)

    def evaluator(self, eval_cfg) -> "LQREvaluator":
        return LQREvaluator(self, eval_cfg)

    def return_quantity(self) -> tuple[float, int]:
        return self.lqr_config.gamma, self.lqr_config.horizon  # lqr_paired_regret's discounted return

    def minari_env_kwargs(self, behaviour) -> dict:  # not a gymnasium env: its spaces only
        import numpy as np
        from gymnasium import spaces

        obs_dim, act_dim = behaviour["observation"].shape[-1], behaviour["action"].shape[-1]
        bound = float(self.lqr_config.action_bound)
        return {"observation_space": spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32),
                "action_space": spaces.Box(-bound, bound, (act_dim,), np.float32)}


class LQREvaluator(Evaluator):
    """The greedy policy's paired regret against the exact optimum (same start states and noise), its return, and
    Q̂'s error against the exact Q* on fresh expert and behaviour samples; :attr:`true_ratio` is the exact ratio."""

    def __init__(self, task: LQRTask, eval_cfg) -> None:
        super().__init__()
        self.task = task
        lqr_config, data_cfg = task.lqr_config, task.data_config
        batch = [min(eval_cfg.q_samples, 10_000)]
        env = make_lqr_env(lqr_config, batch_size=batch, seed=eval_cfg.seed + 1)
        start = data_cfg.behaviour_initial_std  # the behaviour's samples from its own start law (None: the system's)
        env_b = env if start is None else make_lqr_env(lqr_data.behaviour_system(lqr_config, data_cfg),
                                                       batch_size=batch, seed=eval_cfg.seed + 1)
        expert = make_lqr_expert(env, tau=data_cfg.expert_tau)
        behaviour = make_lqr_behaviour(env, gain_scale=data_cfg.behaviour_gain_scale,
                                       noise_std=data_cfg.behaviour_noise_std)
        n = math.ceil(eval_cfg.q_samples / env.batch_size[0] / lqr_config.horizon) * env.batch_size[0] * lqr_config.horizon
        for name, policy, on, seed in (("expert", expert, env, eval_cfg.seed + 2),
                                       ("behaviour", behaviour, env_b, eval_cfg.seed + 3)):
            self.eval_samples[name] = collect_transitions(on, policy, n, seed=seed)[: eval_cfg.q_samples].select(
                "observation", "action"
            )
        self.true_ratio = lqr_true_density_ratio(env, expert, behaviour, behaviour_initial_std=start)

    def evaluate(self, policy, *, episodes: int, seed: int, q_value=None, device=None) -> dict:
        out: dict = {}
        res = lqr_paired_regret(self.task.lqr_config, policy, episodes=episodes, seed=seed)
        for key in ("return", "regret", "optimal_return_paired"):
            out[f"{key}"] = res[key].mean
            out[f"{key}_ci"] = res[key].half_width
            out[f"{key}_stderr"] = res[key].stderr
        out["optimal_return_exact"] = res["optimal_return_exact"]
        for name, samples in self.eval_samples.items() if q_value is not None else ():
            q_hat, action = q_value(samples.to(device))
            q_hat = q_hat.cpu()
            q_star = self.task.lqr_env.optimal_q(samples["observation"].double(), action.cpu().double())
            errs = q_error(q_hat, q_star)
            out[f"q_error_{name}"] = errs["relative_spread_error"]
            out[f"q_bias_{name}"] = errs["bias"]
            out[f"q_mean_{name}"] = q_hat.double().mean().item()
            out[f"q_star_mean_{name}"] = errs["q_true_mean"]
        return out
