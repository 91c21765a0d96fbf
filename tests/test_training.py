"""The two-stage trainer: configs, weights over D, early stopping, results, and exact resume."""
from __future__ import annotations

import json

import pytest
import torch
from omegaconf import OmegaConf

from torchrl_wbrm.training import WBRMConfig, WBRMTrainer, shape_weights, validate_config


def tiny_config(**overrides) -> WBRMConfig:
    cfg = OmegaConf.structured(WBRMConfig)
    base = {
        "env": {"lqr_data": {"behaviour_episodes": 40, "expert_episodes": 20, "parallel_envs": 20}},
        "ratio": {"steps": 30, "batch_size": 64, "eval_every": 10, "num_cells": [16, 16]},
        "q": {"steps": 40, "batch_size": 32, "eval_every": 20, "num_cells": [16, 16], "actor_num_cells": [16, 16]},
        "eval": {"episodes": 50, "train_episodes": 20, "q_samples": 400},
        "logger": {"backend": "", "log_every": 5},
        "checkpoint_every": 10,
        "plots": False,
    }
    cfg = OmegaConf.merge(cfg, base, overrides)
    return OmegaConf.to_object(cfg)


def test_shape_weights_known_answers():
    w = torch.tensor([[0.0], [1.0], [4.0], [16.0]])
    torch.testing.assert_close(shape_weights(w, self_normalise=False), w)
    torch.testing.assert_close(shape_weights(w, temper=0.5, self_normalise=False), torch.tensor([[0.0], [1.0], [2.0], [4.0]]))
    torch.testing.assert_close(shape_weights(w, clip=3.0, self_normalise=False), torch.tensor([[0.0], [1.0], [3.0], [3.0]]))
    mixed = shape_weights(w, mix=0.5, self_normalise=False)  # 0.5 * w / mean(w) + 0.5, mean(w) = 5.25
    torch.testing.assert_close(mixed, 0.5 * w / 5.25 + 0.5)
    assert shape_weights(w).mean().item() == pytest.approx(1.0)
    assert (shape_weights(w, mix=0.2) > 0).all()  # a floor under every weight
    with pytest.raises(ValueError, match="temper"):
        shape_weights(w, temper=0.0)
    with pytest.raises(ValueError, match="non-negative"):
        shape_weights(-w)


@pytest.mark.parametrize(
    "override, match",
    [
        ({"q": {"residual": "cubed"}}, "q.residual='cubed'"),
        ({"q": {"bootstrap": "hard"}}, "q.bootstrap"),
        ({"ratio": {"source": "oracle"}}, "ratio.source"),
        ({"ratio": {"bounds": [2.0, 10.0]}}, "ratio.bounds"),
        ({"ratio": {"temper": 1.5}}, "ratio.temper"),
        ({"q": {"steps": 0}}, "q.steps must be > 0"),
        ({"env": {"kind": "mountain_car"}, "ratio": {"source": "exact"}}, "needs an LQR env"),
    ],
)
def test_config_errors_name_the_setting(override, match):
    cfg = OmegaConf.merge(OmegaConf.structured(WBRMConfig), override)
    with pytest.raises(ValueError, match=match):
        validate_config(OmegaConf.to_object(cfg))


def test_unknown_or_mistyped_keys_fail():
    from omegaconf.errors import ConfigKeyError, ValidationError

    with pytest.raises(ConfigKeyError, match="stepz"):
        OmegaConf.merge(OmegaConf.structured(WBRMConfig), {"q": {"stepz": 3}})
    with pytest.raises(ValidationError, match="steps"):
        OmegaConf.merge(OmegaConf.structured(WBRMConfig), {"q": {"steps": "many"}})


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    torch.set_num_threads(1)
    run_dir = tmp_path_factory.mktemp("run")
    trainer = WBRMTrainer(tiny_config(), run_dir, progress=False)
    results = trainer.run()
    return trainer, results, run_dir


def test_run_writes_results_with_truth_scores(finished_run):
    trainer, results, run_dir = finished_run
    saved = json.loads((run_dir / "results.json").read_text())
    assert saved["env"] == "lqr_exp1" and saved["config"]["q"]["steps"] == 40
    final = saved["final"]
    for key in ("return", "return_ci", "regret", "regret_ci", "q_error_expert", "q_bias_expert", "optimal_return_exact"):
        assert key in final and final[key] == final[key]  # present and not NaN
    assert final["optimal_return_exact"] == pytest.approx(85.4351, abs=1e-4)
    assert final["regret"] > 0  # 40 steps of a 16-unit net are far from optimal ...
    assert final["regret_ci"] < final["return_ci"]  # ... and the pairing makes regret sharper than the return
    assert "ratio_relative_l2" in saved["ratio"] and saved["weights"]["ess"] > 0


def test_weights_are_computed_once_and_self_normalised(finished_run):
    trainer, _, _ = finished_run
    stored = trainer.q_buffer[:]["density_ratio"]
    n_train, n_holdout = trainer.q_train_data.shape[0], trainer.q_holdout.shape[0]
    assert stored.shape == (n_train, 1) and n_train + n_holdout == trainer.datasets.sizes()["transitions"]
    assert set(trainer.q_train_data["episode"].tolist()).isdisjoint(trainer.q_holdout["episode"].tolist())
    assert stored.mean().item() == pytest.approx(1.0, rel=1e-4)
    with torch.no_grad():
        w = trainer.ratio_network(trainer.q_train_data.select("observation", "action"))["density_ratio"]
    torch.testing.assert_close(stored, w / w.mean(), rtol=1e-4, atol=1e-6)
    batch = trainer.q_buffer.sample()
    assert "density_ratio" in batch.keys()


def test_ratio_stage_keeps_the_best_held_out_state(finished_run):
    trainer, results, _ = finished_run
    records = [r for r in trainer.history if r["stage"] == "ratio"]
    best = min(records, key=lambda r: r["held_out_loss"])
    assert results["ratio"]["best_step"] == best["step"]
    assert results["ratio"]["best_held_out_loss"] == pytest.approx(best["held_out_loss"])


def test_early_stopping_stops_the_ratio_stage(tmp_path):
    cfg = tiny_config(ratio={"steps": 400, "eval_every": 5, "patience": 2, "lr": 0.5})
    trainer = WBRMTrainer(cfg, tmp_path, progress=False)
    trainer.run()
    steps = [r["step"] for r in trainer.history if r["stage"] == "ratio"]
    assert max(steps) < 400


@pytest.mark.parametrize("source", ["none", "exact"])
def test_unweighted_and_true_ratio_sources(tmp_path, source):
    trainer = WBRMTrainer(tiny_config(ratio={"source": source}), tmp_path, progress=False)
    results = trainer.run()
    w = trainer.q_buffer[:]["density_ratio"]
    if source == "none":
        assert (w == 1).all() and trainer.ratio_network is None
    else:
        assert w.std() > 0.5 and results["weights"]["ess_fraction"] < 0.5


def _params(trainer):
    return {k: v.clone() for k, v in trainer.q_loss.state_dict().items()}


def test_resume_is_bit_identical(tmp_path):
    torch.set_num_threads(1)
    full = WBRMTrainer(tiny_config(), tmp_path / "full", progress=False)
    full_results = full.run()
    interrupted = WBRMTrainer(tiny_config(), tmp_path / "cut", progress=False)
    assert interrupted.run(until=25) is None  # stopped mid stage 2; checkpoint at step 25
    del interrupted
    resumed = WBRMTrainer(tiny_config(), tmp_path / "cut", progress=False, resume=True)
    assert resumed.state == {"stage": "q", "step": 25}
    resumed_results = resumed.run()
    a, b = _params(full), _params(resumed)
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert resumed_results["final"] == full_results["final"]


def test_resume_refuses_other_data(tmp_path):
    WBRMTrainer(tiny_config(), tmp_path, progress=False).run(until=10)
    with pytest.raises(ValueError, match="data differ"):
        WBRMTrainer(tiny_config(seed=1), tmp_path, progress=False, resume=True)
    with pytest.raises(FileNotFoundError, match="checkpoint"):
        WBRMTrainer(tiny_config(), tmp_path / "empty", progress=False, resume=True)


def test_held_out_bellman_residual_is_reported(finished_run):
    trainer, results, _ = finished_run
    assert results["final"]["held_out_bellman_residual"] > 0


def test_relative_true_ratio_is_bounded_by_one_over_beta(tmp_path):
    trainer = WBRMTrainer(tiny_config(ratio={"source": "exact", "relative_beta": 0.5, "self_normalise": False}), tmp_path, progress=False)
    trainer.run()
    w = trainer.q_buffer[:]["density_ratio"]
    assert w.max().item() <= 2.0 + 1e-6 and w.min().item() >= 0


def test_behaviour_cloning_reference(tmp_path):
    trainer = WBRMTrainer(tiny_config(algo="bc", q={"steps": 200, "eval_every": 200}), tmp_path, progress=False)
    results = trainer.run()
    assert trainer.ratio_network is None and results["algo"] == "bc"
    assert "q_error_expert" not in results["final"]
    # 200 steps of cloning a linear expert already give a small regret on exp1
    assert results["final"]["regret"] < 0.5


def test_ratio_gradient_clipping_bounds_the_step(tmp_path):
    """ratio.grad_clip bounds the norm of each stage-1 gradient step (checked with SGD at lr 1, where step = gradient)."""
    def first_step_change(clip):
        torch.manual_seed(0)
        trainer = WBRMTrainer(tiny_config(ratio={"grad_clip": clip, "lr": 1e-2}), tmp_path / str(clip), progress=False)
        before = [p.detach().clone() for p in trainer.ratio_loss.parameters()]
        trainer.ratio_optim = torch.optim.SGD(trainer.ratio_loss.parameters(), lr=1.0)
        trainer._ratio_step(1)
        return sum((p.detach() - b).norm() ** 2 for p, b in zip(trainer.ratio_loss.parameters(), before)).sqrt().item()

    clipped, free = first_step_change(1e-3), first_step_change(None)
    assert clipped <= 1e-3 + 1e-9  # SGD with lr 1: the step is the clipped gradient, norm <= 1e-3
    assert free > 10 * clipped


def test_summarise_a_method_without_a_q_network():
    from torchrl_wbrm.training.reporting import summarise

    final = {"return": 85.44, "return_ci": 0.1, "optimal_return_exact": 85.4351, "regret": 0.003, "regret_ci": 0.001}
    text = summarise({"env": "lqr_exp1", "seed": 0, "algo": "bc", "final": final, "ratio": {"source": "none"}})
    assert "paired regret 0.0030" in text and "Q̂ error" not in text and "baseline" in text
