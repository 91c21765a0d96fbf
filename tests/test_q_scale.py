"""The ``q_blow_up`` check reads a Q figure for every algo with a Q: the algos on torchrl's losses (DDPG, TD3+BC,
IQL, CQL) report none of their own in training, and a Minari evaluation none either, so the trainer measures the
delivered Q̂'s mean over D's training rows itself (``"q_mean_data"``)."""
from __future__ import annotations

import pytest
import torch

from minari_helpers import mountain_car_datasets
from tests.references import tiny_lqr_config
from torchrl_wbrm.training import WBRMTrainer
from torchrl_wbrm.training.config import WBRMConfig

pytestmark = pytest.mark.usefixtures("single_thread")  # tests/conftest.py: one torch thread per test


@pytest.mark.parametrize("algo", ["ddpg", "td3bc", "iql", "cql", "wbrm"])
def test_every_q_algo_has_a_q_figure_on_minari_data(tmp_path, algo):
    data = mountain_car_datasets()
    cfg = WBRMConfig(env="minari", algo=algo, seed=0)
    m = cfg.env.minari
    m.data_path, m.expert, m.behaviour = data["data_path"], data["expert"], data["behaviour"]
    cfg.ratio.steps, cfg.q.steps, cfg.q.eval_every, cfg.q.select = 20, 20, 20, "last"
    cfg.eval.episodes = cfg.eval.train_episodes = 1
    cfg.plots, cfg.logger.backend = False, ""
    trainer = WBRMTrainer(cfg, tmp_path / algo, progress=False)
    results = trainer.run()
    scale = results["q_scale"]
    assert scale["figure"] is not None and scale["max_abs_q_mean"] is not None
    d = trainer.q_train_data
    with torch.no_grad():
        q, _ = trainer.algo.q_value(d)
    assert trainer.evaluation.q_mean_over_d() == pytest.approx(q.double().mean().item(), rel=1e-6)
    assert scale["max_abs_q_mean"] >= abs(q.double().mean().item()) * (1 - 1e-6)


def test_a_torchrl_loss_blowing_up_is_flagged_by_its_q_over_d(tmp_path):
    """CQL at a learning rate of 100 on the tiny LQR task: its Q̂ over D is far past 10 r_max / (1 − γ)."""
    results = WBRMTrainer(tiny_lqr_config({"q": {"lr_schedule": "constant"}, "baselines": {"cql": {"lr": 100.0}}},
                                          algo="cql"), tmp_path, progress=False).run()
    scale = results["q_scale"]
    assert results["status"] == "finished" and "q_blow_up" in results["flags"]
    assert scale["figure"] == "q_mean_data" and scale["max_abs_q_mean"] > scale["factor"] * scale["bound"]
