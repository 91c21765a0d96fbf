"""``seeds=[...]``: several seeds of one config trained in one process (torchrl_wbrm.training.seeds)."""
from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import torch

from tests import inprocess
from tests.references import tiny_lqr_config
from torchrl_wbrm.evaluation.stats import mean_ci
from torchrl_wbrm.training.config import validate_config
from torchrl_wbrm.training.reporting import load_results
from torchrl_wbrm.training.seeds import run_seeds, summarise_seeds
from torchrl_wbrm.training.trainer import WBRMTrainer

ROOT = Path(__file__).resolve().parents[1]

#: the tiny LQR config (tests/references.py) as recipe overrides
TINY_OVERRIDES = [
    "env.lqr_data.behaviour_episodes=40", "env.lqr_data.expert_episodes=20", "env.lqr_data.parallel_envs=20",
    "ratio.steps=30", "ratio.batch_size=64", "ratio.eval_every=10", "ratio.num_cells=[16,16]",
    "q.steps=40", "q.batch_size=32", "q.eval_every=20", "q.num_cells=[16,16]", "q.actor_num_cells=[16,16]",
    "eval.offline_value=false", "eval.episodes=50", "eval.train_episodes=20", "eval.q_samples=300", "logger.backend=", "logger.log_every=5",
    "plots=false",
]


#: what differs between two runs of one config: the seconds they took
_TIMES = ("data_seconds", "wall_seconds")


def _without_times(results: dict) -> dict:
    return {k: v for k, v in results.items() if k not in _TIMES}


def test_recipe_seeds_equal_separate_runs(tmp_path):
    """``python recipes/wbrm_offline.py seeds=[0,1]``: each seed's results and history are those of a separate run
    with that seed, bit for bit; results.json holds both and their aggregate."""
    run_dir = tmp_path / "two_seeds"
    proc = inprocess.recipe("seeds=[0,1]", *TINY_OVERRIDES, f"hydra.run.dir={run_dir}", cwd=tmp_path,
                            env={**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads((run_dir / "results.json").read_text())
    assert results["kind"] == "seeds" and results["seeds"] == [0, 1]
    assert [r["seed"] for r in results["runs"]] == [0, 1]
    assert all(r["status"] == "finished" for r in results["runs"])
    regrets = [r["final"]["regret"] for r in results["runs"]]
    assert regrets[0] != regrets[1]  # each seed its own data and initialisation
    agg = results["aggregate"]["final"]["regret"]
    ci = mean_ci(regrets)
    assert agg["mean"] == pytest.approx(ci.mean) and agg["half_width"] == pytest.approx(ci.half_width)
    for run in results["runs"]:
        seed = run["seed"]
        assert run["config"]["seed"] == seed and "seeds" not in run["config"]
        assert (run_dir / f"seed{seed}" / "checkpoint.pt").is_file()  # each seed checkpoints as a single run
        alone = WBRMTrainer(tiny_lqr_config(seed=seed), tmp_path / f"alone{seed}", progress=False).run()
        assert _without_times(run) == _without_times(alone), seed
        history = json.loads((run_dir / f"seed{seed}" / "history.json").read_text())
        assert history == json.loads((tmp_path / f"alone{seed}" / "history.json").read_text()), seed
    # the studies read the run as its two seeds' runs, each once, with the history beside each
    records = load_results(run_dir)
    assert sorted(r["seed"] for r in records) == [0, 1]
    assert all(Path(r["_path"]).with_name("history.json").is_file() for r in records)


def test_every_algo_trains_its_seeds_in_one_process(tmp_path):
    cfg = tiny_lqr_config(algo="bc", seeds=[0, 1], q={"steps": 10, "eval_every": 10})
    results = run_seeds(cfg, tmp_path, progress=False)
    assert [r["seed"] for r in results["runs"]] == [0, 1]
    assert json.loads((tmp_path / "results.json").read_text())["aggregate"]["final"]["return"]["n"] == 2
    assert "one seed at a time" not in summarise_seeds(results)


@pytest.mark.parametrize("seeds, message", [([], "non-empty"), ([0, 0], "distinct"), ([-1], ">= 0")])
def test_bad_seeds_are_refused(seeds, message):
    with pytest.raises(ValueError, match=message):
        validate_config(tiny_lqr_config(seeds=seeds))


def test_a_multi_seed_resume_is_a_valid_config():
    validate_config(tiny_lqr_config(seeds=[0, 1], resume="outputs/some_run"))


def test_a_diverging_seed_is_recorded_and_the_others_finish(tmp_path, monkeypatch):
    """Seed 1's Q parameters turned NaN after its setup: seed 1 is recorded as diverged (its own results.json says
    where), seed 0 finishes, and the aggregate is over the finished seed alone."""
    build = WBRMTrainer.__init__

    def poisoned(self, cfg, *args, **kwargs):
        build(self, cfg, *args, **kwargs)
        if self.cfg.seed == 1:
            with torch.no_grad():
                for value in self.algo.loss.value_network_params.values(True, True):
                    value.fill_(float("nan"))

    monkeypatch.setattr(WBRMTrainer, "__init__", poisoned)
    results = run_seeds(tiny_lqr_config(seeds=[0, 1]), tmp_path, progress=False)
    assert results["status"] == "diverged" and results["seeds_diverged"] == [1]
    finished, diverged = results["runs"]
    assert finished["status"] == "finished" and diverged["status"] == "diverged"
    # refused at stage 2's first checkpoint, as a separate run with these parameters is
    assert diverged["diverged"]["stage"] == "q" and diverged["diverged"]["figure"].startswith("parameter ")
    assert json.loads((tmp_path / "seed1" / "results.json").read_text())["status"] == "diverged"
    assert results["aggregate"]["final"]["regret"]["n"] == 1
    assert results["aggregate"]["final"]["regret"]["mean"] == pytest.approx(finished["final"]["regret"])
    assert "seed 1: regret n/a  (diverged)" in summarise_seeds(results)
