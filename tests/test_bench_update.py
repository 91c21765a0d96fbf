"""``benchmarks/bench_update.py``: its plain-PyTorch twin does the project's maths, and every comparison runs at each
width of ``--widths`` (no timings are asserted)."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        spec = importlib.util.spec_from_file_location("bench_update", ROOT / "benchmarks" / "bench_update.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))


def test_the_twin_takes_the_algos_steps(bench):
    """Same batch, same draw of S^e: the same value and actor losses (the default actor loss has the cloning term),
    and parameters equal up to the two Adams' floating-point order."""
    cfg = bench.at_width(bench.resolve_defaults(bench.WBRMConfig()), 8)
    assert cfg.q.expert_bc_alpha
    algo, twin = bench.project_q(cfg, torch.device("cpu"))
    data = bench.lqr_like_data(300, torch.device("cpu"))
    for i in (1, 2, 3, 4):
        batch = data[torch.randint(300, (cfg.q.batch_size,))]
        state = torch.get_rng_state()
        ours = algo.step(batch, i)
        torch.set_rng_state(state)
        value, actor = twin.full_step(bench.twin_tensors(batch), i)
        torch.testing.assert_close(ours["loss_value"], value)
        assert ("loss_actor" in ours) == (actor is not None) == (i % cfg.q.actor_delay == 0)
        if actor is not None:
            torch.testing.assert_close(ours["loss_actor"], actor)
    loss = algo.loss
    for network, params, theirs in ((loss.value_network, loss.value_network_params, twin.q),
                                    (loss.actor_network, loss.actor_network_params, twin.actor)):
        with params.to_module(network):
            ours = {name: p.detach().clone() for name, p in network.module.named_parameters()}
        assert ours.keys() == dict(theirs.named_parameters()).keys()
        for name, p in theirs.named_parameters():
            torch.testing.assert_close(ours[name], p.detach(), rtol=1e-5, atol=1e-6)


def test_every_comparison_runs_at_each_width(bench, capsys):
    results = bench.main(["--iterations", "1", "--rounds", "1", "--widths", "8", "16"])
    out = capsys.readouterr().out
    for width in (8, 16):
        assert set(results[width]) == {"critic", "full", "full_sampled", "whole_step"}
        assert f"=== 2x{width} networks ===" in out and "whole stage-2 step" in out
        assert all(r["ratio"] > 0 for r in results[width]["whole_step"].values())
    assert set(results["ratio"]) == {"ratio", "ratio_sampled"}
