"""Every method (``algo=...``, :mod:`torchrl_wbrm.algos`) through the recipe and its trainer.

- Each algo runs once through ``recipes/wbrm_offline.py`` itself (one Hydra multirun over all of them, tiny
  budget, the recipe's default plots and logger) and its ``results.json``, ``history.json``, figures and CSV logs are
  checked.
- Each trainer discounts with the env's γ (by value for the Bellman-residual family) and sees the right data
  (only ``wbrm`` reads the stage-1 weights).
- Each learns LQR exp1 on the recipe's own config (``configs/wbrm_offline.yaml`` composed by Hydra, so its defaults
  are the recipe's: for ``wbrm`` the learned ŵ with its shaping ``ratio.temper``) with a small budget. The thresholds
  are computed, never typed in (:mod:`tests.references`): the exact regret of the behaviour policy's mean action
  ``a = −½Kx`` (0.083 on exp1; the zero action's is 0.360 and the optimum's 0), and for Q̂ the error of the best
  constant Q (1 by definition of the error, ``RMS(Q̂ − Q*)/std(Q*)``) and of the behaviour policy's exact Q
  (about 4 on expert samples: it is lower than Q* by the behaviour's loss). Where a method does not reach a bar on
  this budget the test is an expected failure (``xfail(strict=True)``: it fails the suite once the method does reach
  it); docs/results/paper_tables.md reports each method's figures at the tables' larger budget.
"""
from __future__ import annotations

import functools
import json
import os
import shutil
import tempfile
from pathlib import Path

import pytest
import torch

from torchrl_wbrm.envs import LQRConfig, make_lqr_env
from torchrl_wbrm.training import WBRMTrainer
from torchrl_wbrm.algos import ALGOS
from torchrl_wbrm.modules import ActionGrid
from torchrl_wbrm.training.config import WBRMConfig, validate_config

from tests import inprocess
from tests.references import ROOT, compose_recipe, lqr_env, policy_q, reference_regrets, relative_q_error
from tests.test_training import tiny_config

#: one xdist worker runs this module (``pytest -n 2 --dist loadfile``): its shared runs are computed once

BELLMAN_FAMILY = ("wbrm", "brm", "fqi", "mabo")  # WeightedBellmanLoss and its subclass: held-out residual, γ by value


# ---------------------------------------------------------------------- the recipe, every algo, plots on
RECIPE_TINY = [
    "env.lqr_data.behaviour_episodes=40", "env.lqr_data.expert_episodes=20", "env.lqr_data.parallel_envs=20",
    "ratio.steps=20", "ratio.eval_every=10", "ratio.num_cells=[16,16]",
    "q.steps=20", "q.eval_every=10", "q.num_cells=[16,16]", "q.actor_num_cells=[16,16]",
    "eval.offline_value=false", "eval.episodes=50", "eval.train_episodes=20", "eval.q_samples=400", "baselines.cql.num_random=2",
]


@pytest.fixture(scope="session")
def recipe_runs(tmp_path_factory):
    """One ``python recipes/wbrm_offline.py -m algo=<all>`` (Hydra's basic launcher, one job after another; run in
    this process, :mod:`tests.inprocess`), with the
    recipe's defaults for plots and logger; returns (the sweep directory, the completed process)."""
    out = tmp_path_factory.mktemp("recipe_all_algos")
    algos = ["wbrm", *sorted(set(ALGOS) - {"wbrm"})]
    proc = inprocess.recipe("-m", f"algo={','.join(algos)}", *RECIPE_TINY, f"hydra.sweep.dir={out}",
                            "hydra.sweep.subdir=${algo}", cwd=ROOT,
                            env={**os.environ, "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1", "WANDB_MODE": "offline"})
    return out, proc


def _is_png(path: Path) -> bool:
    return path.is_file() and path.stat().st_size > 5_000 and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("algo", sorted(ALGOS))
def test_each_algo_writes_results_and_figures_through_the_recipe(recipe_runs, algo):
    out, proc = recipe_runs
    run_dir = out / algo
    assert (run_dir / "results.json").is_file(), f"no results for algo={algo}:\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}"
    saved = json.loads((run_dir / "results.json").read_text())
    assert saved["algo"] == saved["config"]["algo"] == algo and saved["env"] == "lqr_exp1"
    final = saved["final"]
    for key in ("return", "return_ci", "regret", "regret_ci", "optimal_return_exact"):
        assert key in final and final[key] == final[key], key  # present and not NaN
    assert ("q_error_expert" in final) == (algo != "bc")
    assert ("held_out_bellman_residual" in final) == (algo in BELLMAN_FAMILY)
    assert saved["ratio"]["source"] == ("learned" if algo == "wbrm" else "none")
    assert saved["config"]["plots"] is True  # the recipe's default
    for figure in ("training_curve.png", "evaluation.png"):
        assert _is_png(run_dir / figure), (algo, figure)
    history = json.loads((run_dir / "history.json").read_text())
    assert [r["step"] for r in history if r["stage"] == "q"] == [10, 20]
    assert any((run_dir / "logs").rglob("*.csv"))  # the recipe's default csv logger
    assert (run_dir / "checkpoint.pt").is_file()
    assert proc.stdout.count("paired regret") == len(ALGOS)  # the recipe's summary, once per algo


# ---------------------------------------------------------------------- γ and data, per algo
def _discount(loss) -> float:
    return float(loss.value_estimator.gamma)


@pytest.mark.parametrize("algo", sorted(ALGOS))
def test_each_algo_discounts_with_the_env_gamma_and_reads_its_data(tmp_path, single_thread, algo):
    trainer = WBRMTrainer(tiny_config(algo=algo), tmp_path, progress=False)
    gamma = trainer.cfg.env.lqr.gamma  # the env's 0.9, from the env config rather than from the trainer
    assert trainer.gamma == pytest.approx(gamma)
    if algo != "bc":
        assert _discount(trainer.q_loss) == pytest.approx(gamma, abs=1e-7)
    assert (trainer.ratio_network is not None) == (algo == "wbrm")
    if algo == "wbrm":
        return  # its weights: tests/test_training.py
    trainer._build_q_buffer()
    batch = trainer.q_buffer.sample()
    if algo == "bc":
        assert set(batch.keys()) >= {"observation", "action"} and "next" not in batch.keys()  # S^e, not D
        return
    assert (trainer.q_buffer[:]["density_ratio"] == 1).all()  # baselines never see the stage-1 weights
    if algo in BELLMAN_FAMILY:  # by value: Y − r = γ (1 − terminated) max Q_target(x', ·)
        loss = trainer.q_loss
        with torch.no_grad():
            _, target = loss.bellman_error(batch)
            next_value = loss.next_state_value(batch)
        not_terminated = (~batch["next", "terminated"].bool()).float().reshape(-1)
        reward = batch["next", "reward"].reshape(-1)
        torch.testing.assert_close(target - reward, gamma * not_terminated * next_value)
        assert next_value.abs().min() > 1  # Q starts at mean(r)/(1 − γ): a wrong γ cannot hide behind Q ≈ 0


# ---------------------------------------------------------------------- learning LQR exp1 on the recipe's config
# A small budget: 1,000 behaviour episodes (D ≈ 9,000 transitions after the split), 500 expert episodes, 64-unit
# networks (the recipe's activation and every other default), 1,000 steps; 1,000 paired evaluation episodes.
LEARN_BUDGET = [
    "env=lqr_exp1",
    "env.lqr_data.behaviour_episodes=1000", "env.lqr_data.expert_episodes=500",
    "ratio.steps=300", "ratio.num_cells=[64,64]",
    "q.steps=1000", "q.eval_every=1000", "q.num_cells=[64,64]", "q.actor_num_cells=[64,64]",
    "eval.episodes=1000", "eval.q_samples=2000",
    "checkpoint_every=0", "plots=false", "logger=none",
]
#: CQL costs several times more per step (two Q networks, sampled actions): fewer steps and 4 sampled actions, not 10
EXTRA = {"cql": ["baselines.cql.num_random=4", "q.steps=500", "q.eval_every=500"],
         # the recipe's GELU Q fits Q̂ more slowly at this small budget than SiLU did: after 1,000 steps WBRM's Q̂
         # error on expert samples was 0.55 and BRM's 0.66, against the bar of 0.50 below; 2,000 steps clear it
         "wbrm": ["q.steps=2000", "q.eval_every=2000"],
         "brm": ["q.steps=2000", "q.eval_every=2000"],
         "iql": ["q.steps=1500", "q.eval_every=1500"]}

#: a Q-learning method must beat the behaviour policy's mean action by this factor in regret ...
REGRET_FACTOR = 2.0
#: ... and its Q̂ must beat the better of the constant-Q and behaviour-Q baselines by this factor
Q_FACTOR = 2.0


_RUN_DIRS: list[str] = []


@pytest.fixture(scope="session", autouse=True)
def _forget_learning_runs():
    """The learning runs are cached for this module's tests: drop them (and their run directories) at the end of the
    session (session-scoped: under xdist a worker may interleave other modules' tests, and a module-scoped finaliser
    would then drop the cache between this module's tests and train again)."""
    yield
    _learned.cache_clear()
    _data_cache.cache_clear()
    for run_dir in _RUN_DIRS:
        shutil.rmtree(run_dir, ignore_errors=True)


@functools.cache
def _data_cache() -> str:
    """The learning runs' one dataset (LQR exp1, seed 0): collected by the first run, loaded by the others."""
    _RUN_DIRS.append(tempfile.mkdtemp(prefix="learn_data_cache_"))
    return _RUN_DIRS[-1]


@functools.cache
def _learned(algo: str) -> dict:
    """Train ``algo`` once (shared by the regret and the Q̂ tests); returns its trainer, figures and the baselines."""
    torch.set_num_threads(1)
    cfg = compose_recipe(f"algo={algo}", *LEARN_BUDGET, *EXTRA.get(algo, []), f"data_cache={_data_cache()}")
    _RUN_DIRS.append(tempfile.mkdtemp(prefix=f"learn_{algo}_"))
    trainer = WBRMTrainer(cfg, _RUN_DIRS[-1], progress=False)
    results = trainer.run()
    env = lqr_env(trainer.task.lqr_config)
    _, K = env.riccati()
    data = trainer.cfg.env.lqr_data
    samples = trainer.evaluation.eval_samples["expert"]
    q_star = env.optimal_q(samples["observation"].double(), samples["action"].double())
    q_behaviour = policy_q(env, data.behaviour_gain_scale * K, data.behaviour_noise_std)(samples["observation"],
                                                                                         samples["action"])
    return {
        "trainer": trainer,
        "final": results["final"],
        "weights": results["weights"],
        "ratio": results["ratio"],
        "config": results["config"],
        "regrets": reference_regrets(trainer.task.lqr_config, behaviour_gain_scale=data.behaviour_gain_scale),
        "q_constant": relative_q_error(torch.full_like(q_star, q_star.mean().item()), q_star),
        "q_behaviour": relative_q_error(q_behaviour, q_star),
    }


def _finding(reason: str):
    return pytest.mark.xfail(strict=True, reason=f"finding at this test's budget: {reason}")


REGRET_CASES = [
    "wbrm", "brm", "fqi", "ddpg", "bc", "iql",  # IQL reaches the bar since the cosine schedule is the default
    "td3bc",  # since its actions are rescaled to [-1, 1] (the paper's units: its cloning term 25x weaker on [-5, 5]^2)
    pytest.param("dqn", marks=_finding("DQN's greedy argmax over 441 grid actions picks unvisited overestimates")),
    pytest.param("cql", marks=_finding("CQL's conservative actor stays near the behaviour's actions")),
    pytest.param("mabo", marks=_finding("MABO's |mean w δ|, one noisy moment per minibatch, learns slowly")),
]
Q_CASES = [
    "wbrm", "brm", "ddpg", "dqn",
    pytest.param("fqi", marks=_finding("FQI's 20 hard target updates in 1,000 steps leave Q̂ short of Q*")),
    pytest.param("td3bc", marks=_finding("TD3+BC's Q̂ is pulled towards the behaviour's values")),
    pytest.param("iql", marks=_finding("IQL's expectile target underestimates Q* by design")),
    pytest.param("cql", marks=_finding("CQL's conservative penalty underestimates Q* by design")),
    pytest.param("mabo", marks=_finding("MABO's Q̂ error stays near the constant-Q baseline")),
]


@pytest.mark.slow
@pytest.mark.parametrize("algo", REGRET_CASES)
def test_each_method_beats_the_behaviour_policy_in_regret(single_thread, algo):
    run = _learned(algo)
    refs, final = run["regrets"], run["final"]
    assert refs["optimum"] < refs["behaviour_mean"] < refs["zero_action"]  # the computed reference points
    threshold = refs["behaviour_mean"] / REGRET_FACTOR
    assert final["regret"] + final["regret_ci"] < threshold, (final["regret"], final["regret_ci"], threshold)


FLOOR_CASES = [
    *sorted(set(ALGOS) - {"dqn", "mabo"}),
    pytest.param("dqn", marks=_finding("DQN's greedy argmax over 441 grid actions picks unvisited overestimates")),
    pytest.param("mabo", marks=_finding("MABO with the cosine schedule at this budget ends worse than the zero "
                                        "action (regret 2.7; 0.049 with a constant rate)")),
]


@pytest.mark.slow
@pytest.mark.parametrize("algo", FLOOR_CASES)
def test_each_method_learns_more_than_the_zero_action(single_thread, algo):
    """A floor below the bar above, for the methods that miss that bar: a run that learned nothing acts about like
    a ≡ 0 (the networks start near it), so a broken update is caught here too."""
    run = _learned(algo)
    threshold = run["regrets"]["zero_action"] / REGRET_FACTOR
    assert run["final"]["regret"] + run["final"]["regret_ci"] < threshold, (run["final"]["regret"], threshold)


@pytest.mark.slow
@pytest.mark.parametrize("algo", Q_CASES)
def test_each_q_method_estimates_q_star_better_than_the_baselines(single_thread, algo):
    run = _learned(algo)
    assert run["q_constant"] == pytest.approx(1.0, abs=1e-3) and run["q_behaviour"] > run["q_constant"]
    threshold = min(run["q_constant"], run["q_behaviour"]) / Q_FACTOR
    assert run["final"]["q_error_expert"] < threshold, (run["final"]["q_error_expert"], threshold)
    assert run["final"]["q_error_behaviour"] < threshold, (run["final"]["q_error_behaviour"], threshold)


@pytest.mark.slow
def test_wbrm_learns_with_the_recipes_learned_and_shaped_weights(single_thread):
    """The paper's method as the recipe runs it: stage 1 fitted ŵ (early stopping on held-out loss), the recipe's
    shaping (``ratio.temper``) applied to the stored weights; its regret and Q̂ bars are checked above."""
    from torchrl_wbrm.ratio import shape_weights

    run = _learned("wbrm")
    recipe = compose_recipe().ratio  # the recipe's stage-1 defaults, whatever they are
    trainer = run["trainer"]
    assert trainer.cfg.ratio.source == "learned" and run["ratio"]["source"] == "learned"
    assert (trainer.cfg.ratio.temper, trainer.cfg.ratio.clip, trainer.cfg.ratio.mix) == (recipe.temper, recipe.clip, recipe.mix)
    assert 0 < run["ratio"]["best_step"] <= run["ratio"]["steps_run"]
    # the weights over D are the fitted network's ŵ, shaped as the recipe says (by value)
    d = trainer.q_buffer[:]
    with torch.no_grad():
        w = trainer.ratio_network(d.select("observation", "action").clone())["density_ratio"]
    expected = shape_weights(w, temper=recipe.temper, clip=recipe.clip, mix=recipe.mix, self_normalise=recipe.self_normalise)
    torch.testing.assert_close(d["density_ratio"], expected.to(d["density_ratio"].dtype), rtol=1e-4, atol=1e-6)
    assert d["density_ratio"].std() > 0.05  # not all ones: the weighting is on


# ---------------------------------------------------------------------- config and grid
def test_algo_choice_is_validated():
    from omegaconf import OmegaConf

    cfg = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(WBRMConfig), {"algo": "sac"}))
    with pytest.raises(ValueError, match="algo='sac'"):
        validate_config(cfg)
    cfg = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(WBRMConfig), {"baselines": {"iql": {"expectile": 1.0}}}))
    with pytest.raises(ValueError, match="expectile"):
        validate_config(cfg)


def test_action_grid_is_the_env_discretizer_and_round_trips():
    grid = ActionGrid.from_lqr_env(LQRConfig(), 5)  # bound 5: bin medians -4, -2, 0, 2, 4
    torch.testing.assert_close(grid.values, torch.tensor([[-4.0, -2.0, 0.0, 2.0, 4.0]] * 2))
    index = torch.arange(grid.num_actions)
    assert grid.num_actions == 25
    torch.testing.assert_close(grid.index(grid(index)), index)
    # nearest grid point per coordinate, coordinate 0 most significant: (0.3, -4.2) -> (0, -4) -> 2 * 5 + 0
    assert grid.index(torch.tensor([[0.3, -4.2]])).item() == 10
    # the env's ActionDiscretizer maps the per-coordinate indices (2, 0) to the same action
    env = make_lqr_env("exp1", discretize_actions=5, seed=0)
    td = env.reset().set("action", torch.tensor([2, 0]))
    continuous = env.transform.inv(td.clone())["action"]
    torch.testing.assert_close(continuous, grid(torch.tensor(10)))
