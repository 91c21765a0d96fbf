"""The two-stage trainer: configs, weights over D, early stopping, results, and exact resume."""
from __future__ import annotations

import json
import math

import pytest
import torch
from omegaconf import OmegaConf

from torchrl_wbrm.ratio import shape_weights
from torchrl_wbrm.training import WBRMConfig, WBRMTrainer, validate_config

from tests.references import policy_q, reference_regrets, relative_q_error


def tiny_config(**overrides) -> WBRMConfig:
    cfg = OmegaConf.structured(WBRMConfig)
    base = {
        "env": {"lqr_data": {"behaviour_episodes": 40, "expert_episodes": 20, "parallel_envs": 20}},
        "ratio": {"steps": 30, "batch_size": 64, "eval_every": 10, "num_cells": [16, 16], "temper": 1.0},
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
        ({"env": {"kind": "mountain_car"}, "ratio": {"source": "exact"}}, "needs an env whose exact density ratio is known"),
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
    assert final["optimal_return_exact"] == pytest.approx(reference_regrets("exp1")["optimal_return"], abs=1e-9)
    assert final["regret_ci"] < final["return_ci"]  # the pairing makes regret sharper than the return
    assert final["regret"] == pytest.approx(final["optimal_return_paired"] - final["return"], abs=1e-9)
    assert "ratio_relative_l2" in saved["ratio"] and saved["weights"]["ess"] > 0


class _LinearPolicy(torch.nn.Module):
    def __init__(self, gain: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("gain", gain.float())

    def forward(self, observation):
        return -observation @ self.gain.T


def test_evaluation_scores_known_policies_at_their_exact_figures(finished_run):
    """The trainer's evaluation, fed policies and Q functions whose figures are known exactly, reports those figures:
    the paired regret of a ≡ 0 and of the behaviour's mean action −½Kx (LQREnv.policy_return), Q̂ = Q* (error 0) and
    Q̂ = Q of the behaviour policy (its error computed here)."""
    from tensordict.nn import TensorDictModule

    trainer = finished_run[0]
    env = trainer.task.lqr_env
    _, K = env.riccati()
    exact = reference_regrets(trainer.task.lqr_config)
    actor, q_value, episodes = trainer.algo.policy, trainer.algo.q_value, trainer.cfg.eval.episodes
    try:
        trainer.cfg.eval.episodes = 1000
        for gain, name in ((torch.zeros_like(K), "zero_action"), (0.5 * K, "behaviour_mean")):
            trainer.algo.policy = TensorDictModule(_LinearPolicy(gain), in_keys=["observation"], out_keys=["action"])
            trainer.algo.q_value = lambda td: (env.optimal_q(td["observation"].double(), td["action"].double()).reshape(-1),
                                               td["action"])
            final = trainer.evaluate(final=True)
            assert abs(final["regret"] - exact[name]) < 4 * final["regret_stderr"] + 1e-3, (name, final["regret"], exact[name])
            assert final["q_error_expert"] < 1e-6 and final["q_error_behaviour"] < 1e-6
        q_b = policy_q(env, 0.5 * K, 0.5)
        trainer.algo.q_value = lambda td: (q_b(td["observation"], td["action"]).reshape(-1), td["action"])
        final = trainer.evaluate(final=True)
        samples = trainer.evaluation.eval_samples["expert"]
        q_star = env.optimal_q(samples["observation"].double(), samples["action"].double())
        expected = relative_q_error(q_b(samples["observation"], samples["action"]), q_star)
        assert final["q_error_expert"] == pytest.approx(expected, rel=1e-6) and expected > 0.05
    finally:
        trainer.algo.policy, trainer.algo.q_value, trainer.cfg.eval.episodes = actor, q_value, episodes


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


def test_early_stopping_stops_the_ratio_stage_and_restores_its_best_state(tmp_path):
    """Stage 1 stops after ``patience`` evaluations without improvement and ends with the network of its best
    held-out evaluation, not its last: recomputed here from the network, the held-out loss is the best one recorded,
    and the weights stored over D come from that network."""
    cfg = tiny_config(ratio={"steps": 400, "eval_every": 5, "patience": 2, "lr": 0.05}, q={"steps": 10, "eval_every": 10})
    trainer = WBRMTrainer(cfg, tmp_path, progress=False)
    results = trainer.run()
    records = [r for r in trainer.history if r["stage"] == "ratio"]
    assert records[-1]["step"] < 400
    best = min(records, key=lambda r: r["held_out_loss"])
    assert records[-1]["held_out_loss"] > best["held_out_loss"] + 1e-4  # the last state is not the best one ...
    with torch.no_grad():
        now = trainer.ratio_fitter.loss_module(trainer.ratio_fitter.holdout)["loss_density_ratio"].item()
    assert now == pytest.approx(best["held_out_loss"], abs=1e-6)  # ... and the network holds the best one
    assert results["ratio"]["best_step"] == best["step"]
    with torch.no_grad():
        w = trainer.ratio_network(trainer.q_train_data.select("observation", "action"))["density_ratio"]
    torch.testing.assert_close(trainer.q_buffer[:]["density_ratio"], w / w.mean(), rtol=1e-4, atol=1e-6)


def _true_ratio_by_hand(env, observation, action, *, expert, behaviour, log=False):
    """dP^e/dP^b at (x, a) (its log with ``log``): each occupancy is the uniform mixture over the 20 steps of
    N(0, C_t), with C_t the state-action covariances of a = −gKx + N(0, σ²I); Gaussian densities by
    torch.distributions."""
    _, K = env.riccati()
    z = torch.cat([observation, action], -1).double()

    def log_density(scale, std):
        covs = env.state_action_covariances(scale * K, std)
        logs = torch.stack([torch.distributions.MultivariateNormal(torch.zeros(len(c), dtype=torch.float64), c).log_prob(z)
                            for c in covs], -1)
        return torch.logsumexp(logs, -1) - math.log(len(covs))

    log_w = log_density(*expert) - log_density(*behaviour)
    return log_w if log else log_w.exp()


def test_unweighted_source_stores_ones(tmp_path):
    trainer = WBRMTrainer(tiny_config(ratio={"source": "none"}), tmp_path, progress=False)
    trainer._build_q_buffer()
    assert (trainer.q_buffer[:]["density_ratio"] == 1).all() and trainer.ratio_network is None


@pytest.mark.parametrize("temper", [1.0, 0.25])
def test_exact_source_stores_the_true_ratio_expert_over_behaviour(tmp_path, temper):
    """ratio.source=exact stores dP^e/dP^b (expert over behaviour, by value), shaped and self-normalised as set."""
    trainer = WBRMTrainer(tiny_config(ratio={"source": "exact", "temper": temper}), tmp_path, progress=False)
    data = trainer.cfg.env.lqr_data
    policies = dict(expert=(1 - data.expert_tau, data.expert_tau),
                    behaviour=(data.behaviour_gain_scale, data.behaviour_noise_std))
    # the trainer's exact ratio by value, in log space (finite whichever way round it is computed), on expert and
    # behaviour samples: log dP^e/dP^b, not its negative
    for samples in (trainer.datasets.expert_samples[:], trainer.q_train_data):
        log_w = trainer.evaluation.true_ratio.module.log_ratio(samples["observation"], samples["action"]).reshape(-1)
        expected = _true_ratio_by_hand(trainer.task.lqr_env, samples["observation"], samples["action"], log=True, **policies)
        torch.testing.assert_close(log_w, expected, rtol=1e-6, atol=1e-6)
    trainer._build_q_buffer()
    d = trainer.q_buffer[:]
    w = _true_ratio_by_hand(trainer.task.lqr_env, d["observation"], d["action"], **policies)
    torch.testing.assert_close(d["density_ratio"].double().squeeze(-1), w**temper / (w**temper).mean(), rtol=1e-4, atol=1e-7)
    # the direction: the ratio is large where the action is near the expert's −0.95Kx and small far from it
    _, K = trainer.task.lqr_env.riccati()
    distance = (d["action"].double() + d["observation"].double() @ (policies["expert"][0] * K).T).norm(dim=-1)
    near, far = d["density_ratio"].squeeze(-1)[distance < 0.1], d["density_ratio"].squeeze(-1)[distance > 1.0]
    assert near.min() > 1 > far.max()
    e = trainer.datasets.expert_samples[:]
    assert _true_ratio_by_hand(trainer.task.lqr_env, e["observation"], e["action"], **policies).mean() > 10  # E_e[w] ≫ 1


def _params(trainer):
    return {k: v.clone() for k, v in trainer.q_loss.state_dict().items()}


@pytest.mark.parametrize("q", [{}, {"expert_bc_from_d": True}], ids=["default", "expert_bc_from_d"])
def test_resume_is_bit_identical(tmp_path, q):
    """Also with D's expert-like episodes in the actor's cloning set: the resumed run selects them again."""
    torch.set_num_threads(1)
    full = WBRMTrainer(tiny_config(q=q), tmp_path / "full", progress=False)
    full_results = full.run()
    if q:
        assert full_results["weights"]["expert_like_episodes"] > 0
    interrupted = WBRMTrainer(tiny_config(q=q), tmp_path / "cut", progress=False)
    assert interrupted.run(until=25) is None  # stopped mid stage 2; checkpoint at step 25
    del interrupted
    resumed = WBRMTrainer(tiny_config(q=q), tmp_path / "cut", progress=False, resume=True)
    assert resumed.state == {"stage": "q", "step": 25}
    resumed_results = resumed.run()
    a, b = _params(full), _params(resumed)
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert resumed_results["final"] == full_results["final"]


def test_resume_from_a_stage_1_checkpoint_is_bit_identical(tmp_path):
    """Interrupted during the ratio stage (at step 16; the last checkpoint is at step 10), resumed, it ends with the
    same ratio network, early-stopping record, weights over D, Q, actor and results as an uninterrupted run."""
    torch.set_num_threads(1)
    cfg = dict(ratio={"steps": 30, "eval_every": 5}, checkpoint_every=10)
    full = WBRMTrainer(tiny_config(**cfg), tmp_path / "full", progress=False)
    full_results = full.run()
    cut = WBRMTrainer(tiny_config(**cfg), tmp_path / "cut", progress=False)
    ratio_step, steps = cut.ratio_fitter.step, []

    def interrupted():
        steps.append(len(steps) + 1)
        if steps[-1] == 16:
            raise KeyboardInterrupt
        return ratio_step()

    cut.ratio_fitter.step = interrupted
    with pytest.raises(KeyboardInterrupt):
        cut.run()
    del cut
    resumed = WBRMTrainer(tiny_config(**cfg), tmp_path / "cut", progress=False, resume=True)
    assert resumed.state == {"stage": "ratio", "step": 10}
    resumed_results = resumed.run()
    for a, b in ((full.ratio_network.state_dict(), resumed.ratio_network.state_dict()), (_params(full), _params(resumed))):
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert torch.equal(full.q_buffer[:]["density_ratio"], resumed.q_buffer[:]["density_ratio"])
    assert resumed_results["ratio"] == full_results["ratio"] and resumed_results["final"] == full_results["final"]


def test_resume_refuses_other_data(tmp_path):
    WBRMTrainer(tiny_config(), tmp_path, progress=False).run(until=10)
    with pytest.raises(ValueError, match="seed: 0 -> 1"):  # refused before any data are collected
        WBRMTrainer(tiny_config(seed=1), tmp_path, progress=False, resume=True)
    with pytest.raises(FileNotFoundError, match=r"no checkpoint\.pt in .*empty"):
        WBRMTrainer(tiny_config(), tmp_path / "empty", progress=False, resume=True)


def test_held_out_bellman_residual_is_reported(finished_run):
    trainer, results, _ = finished_run
    assert results["final"]["held_out_bellman_residual"] > 0


def test_relative_true_ratio_is_bounded_by_one_over_beta(tmp_path):
    trainer = WBRMTrainer(tiny_config(ratio={"source": "exact", "relative_beta": 0.5, "self_normalise": False}), tmp_path, progress=False)
    trainer.run()
    w = trainer.q_buffer[:]["density_ratio"]
    assert w.max().item() <= 2.0 + 1e-6 and w.min().item() >= 0


def test_ratio_gradient_clipping_bounds_the_step(tmp_path):
    """ratio.grad_clip bounds the norm of each stage-1 gradient step (checked with SGD at lr 1, where step = gradient)."""
    def first_step_change(clip):
        torch.manual_seed(0)
        trainer = WBRMTrainer(tiny_config(ratio={"grad_clip": clip, "lr": 1e-2}), tmp_path / str(clip), progress=False)
        before = [p.detach().clone() for p in trainer.ratio_fitter.loss_module.parameters()]
        trainer.ratio_fitter.optimizer = torch.optim.SGD(trainer.ratio_fitter.loss_module.parameters(), lr=1.0)
        trainer.ratio_fitter.step()
        params = trainer.ratio_fitter.loss_module.parameters()
        return sum((p.detach() - b).norm() ** 2 for p, b in zip(params, before)).sqrt().item()

    clipped, free = first_step_change(1e-3), first_step_change(None)
    assert clipped <= 1e-3 + 1e-9  # SGD with lr 1: the step is the clipped gradient, norm <= 1e-3
    assert free > 10 * clipped


def test_summarise_a_method_without_a_q_network():
    from torchrl_wbrm.training.reporting import summarise

    final = {"return": 85.44, "return_ci": 0.1, "optimal_return_exact": 85.4351, "regret": 0.003, "regret_ci": 0.001}
    text = summarise({"env": "lqr_exp1", "seed": 0, "algo": "bc", "final": final, "ratio": {"source": "none"}})
    assert "paired regret 0.0030" in text and "Q̂ error" not in text and "baseline" in text
