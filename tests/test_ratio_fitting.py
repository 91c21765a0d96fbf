"""Stage 1's verdict is one rule, the fitter's (:meth:`DensityRatioFitter.verdict`); the trainer flags the run with it.

Known answer: a ratio network that outputs the constant c scores ``c^{3/2} − 3 c^{1/2}`` under the paper's loss
(α = ½), above the ``−2`` of ŵ ≡ 1 for every c ≠ 1 (``−√2`` for c = 2). A fit that hands such a network on is
flagged ``ratio_worse_than_uniform`` in ``results.json`` and in the console summary; a fit that learns is not.
"""
from __future__ import annotations

import json
import math

import pytest
import torch
from tensordict import TensorDict

from tests.references import tiny_lqr_config
from torchrl_wbrm.modules import DensityRatioNetwork
from torchrl_wbrm.objectives import RobustDensityRatioLoss
from torchrl_wbrm.ratio import DensityRatioFitter, compute_density_ratio, fit_density_ratio
from torchrl_wbrm.training import WBRMTrainer
from torchrl_wbrm.training.results import json_safe
from torchrl_wbrm.training.reporting import summarise

pytestmark = pytest.mark.usefixtures("single_thread")  # tests/conftest.py: one torch thread per test


def _samples(n: int, std: float, seed: int) -> TensorDict:
    """1-d states; the action ``-x`` plus noise of ``std`` (the expert's is small, the behaviour's large)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, 1, generator=g)
    return TensorDict({"observation": x, "action": -x + std * torch.randn(n, 1, generator=g)}, [n])


def _make_constant(network: DensityRatioNetwork, c: float) -> DensityRatioNetwork:
    """Make ``network`` output ŵ = c everywhere: its last layer's weights 0, its bias the pre-image of c."""
    head = network.module
    low, _ = head.bounded.bounds
    assert head.bounded.parameterisation == "softplus"
    with torch.no_grad():
        head.mlp[-1].weight.zero_()
        head.mlp[-1].bias.fill_(math.log(math.expm1(c - low)) - head.bounded.offset)
    return network


def test_a_constant_two_is_handed_on_and_flagged_worse_than_uniform():
    behaviour, expert = _samples(400, 1.0, 1), _samples(200, 0.3, 2)
    network = _make_constant(DensityRatioNetwork(1, 1, num_cells=(8,)), 2.0)
    optimiser = torch.optim.SGD(network.parameters(), lr=0.0)  # the fit cannot move
    fitter = DensityRatioFitter(network, behaviour, expert, batch_size=64, optimizer=optimiser)
    fit = fitter.fit(steps=20, eval_every=5)
    verdict = fit.verdict
    assert verdict["uniform_held_out_loss"] == pytest.approx(-2.0, abs=1e-6)
    assert verdict["best_held_out_loss"] == pytest.approx(-math.sqrt(2.0), abs=1e-5)
    assert fit.ratio_worse_than_uniform and verdict["worse_than_uniform"] and fitter.ratio_worse_than_uniform
    assert not fit.ratio_collapse  # it did not get worse: it never moved
    assert verdict["flags"] == ["ratio_worse_than_uniform"]
    assert "-1.41421" in verdict["worse_than_uniform_reason"] and "-2 of ŵ ≡ 1" in verdict["worse_than_uniform_reason"]


def test_a_fit_that_learns_is_not_flagged():
    behaviour, expert = _samples(2000, 1.0, 1), _samples(1000, 0.3, 2)
    fit = fit_density_ratio(behaviour, expert, steps=200, eval_every=20, batch_size=128, num_cells=(16,), lr=3e-3)
    assert fit.best_loss < fit.verdict["uniform_held_out_loss"] - 0.1
    assert not fit.ratio_worse_than_uniform and not fit.ratio_collapse and fit.verdict["flags"] == []


@pytest.mark.parametrize("options", [{"alpha": 0.5}, {"alpha": 2.0}, {"alpha": "kl"}, {"alpha": 0.5, "relative_beta": 0.3},
                                     {"alpha": 0.5, "non_negative_correction": 0.5},
                                     {"alpha": 1.0, "normalisation_coefficient": 1.0}])
def test_the_uniform_reference_is_the_loss_of_w_equal_to_one(options):
    """ŵ ≡ 1's held-out loss is the loss of ŵ ≡ 1: the population value ``1 − (1 + 1/α)`` (``1`` for KL),
    whatever the loss's options, and the loss itself scores a network that outputs 1 the same."""
    behaviour, expert = _samples(300, 1.0, 1), _samples(150, 0.3, 2)
    network = _make_constant(DensityRatioNetwork(1, 1, num_cells=(8,)), 1.0)
    fitter = DensityRatioFitter(RobustDensityRatioLoss(network, **options), behaviour, expert, batch_size=32)
    expected = 1.0 if options["alpha"] == "kl" else 1.0 - (1.0 + 1.0 / options["alpha"])
    assert fitter.uniform_loss == pytest.approx(expected, abs=1e-6)
    assert fitter.start_loss == pytest.approx(fitter.uniform_loss, abs=1e-5)
    assert not fitter.verdict()["worse_than_uniform"]


def test_the_run_is_flagged_in_results_and_console_when_stage_1_hands_on_a_worse_fit(tmp_path, monkeypatch):
    import torchrl_wbrm.training.parts as parts

    def constant_two(*args, **kwargs):
        return _make_constant(DensityRatioNetwork(*args, **kwargs), 2.0)

    monkeypatch.setattr(parts, "DensityRatioNetwork", constant_two)
    # a learning rate too small to move it (Adam's steps are about lr): the fitter hands on the constant 2
    trainer = WBRMTrainer(tiny_lqr_config(ratio={"lr": 1e-9}), tmp_path, progress=False)
    results = trainer.run()
    assert "ratio_worse_than_uniform" in results["flags"] and "ratio_collapse" not in results["flags"]
    check = results["ratio"]["check"]
    assert check["best_step"] == 0 and check["best_held_out_loss"] == pytest.approx(-math.sqrt(2.0), abs=1e-4)
    assert check["uniform_held_out_loss"] == pytest.approx(-2.0, abs=1e-6) and check["worse_than_uniform"]
    saved = json.loads((tmp_path / "results.json").read_text())
    assert "ratio_worse_than_uniform" in saved["flags"] and saved["ratio"]["check"]["worse_than_uniform"]
    lines = [line for line in summarise(saved).splitlines() if line.startswith("FLAG ratio_worse_than_uniform")]
    assert len(lines) == 1 and "handed on ŵ (step 0) whose held-out loss -1.4142" in lines[0]


def test_the_trainer_reads_the_fitters_verdict_and_a_default_run_is_not_flagged(tmp_path):
    trainer = WBRMTrainer(tiny_lqr_config(), tmp_path, progress=False)
    results = trainer.run()
    assert "ratio_worse_than_uniform" not in results["flags"] and "ratio_collapse" not in results["flags"]
    assert "FLAG ratio" not in summarise(results)
    w = compute_density_ratio(trainer.ratio_network, trainer.q_train_data.clone(), chunk_size=8192)
    assert results["ratio"]["check"] == json_safe(trainer.ratio_fitter.verdict(w))
    assert results["ratio"]["check"]["best_held_out_loss"] < results["ratio"]["check"]["uniform_held_out_loss"]
