"""q.compile=true: the compiled losses equal the eager ones on a fixed batch (to 1e-5), and the trainer accepts it.

Compiling takes a minute on a loaded 2-core machine, hence the ``slow`` mark; no timings are asserted."""
from __future__ import annotations

import copy

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded

from torchrl_wbrm.modules import make_deterministic_actor, make_q_network
from torchrl_wbrm.objectives import WeightedBellmanLoss
from torchrl_wbrm.objectives._compiled import CompiledBellmanLosses

SPEC = Bounded(-2.0, 2.0, (2,))


def _batch(n=64, seed=0):
    g = torch.Generator().manual_seed(seed)
    term = torch.rand(n, 1, generator=g) < 0.2
    return TensorDict({
        "observation": torch.randn(n, 3, generator=g), "action": 2 * torch.rand(n, 2, generator=g) - 1,
        "density_ratio": torch.rand(n, 1, generator=g) + 0.1,
        "next": {"observation": torch.randn(n, 3, generator=g), "reward": 5 + torch.randn(n, 1, generator=g),
                 "done": term.clone(), "terminated": term},
    }, [n])


@pytest.fixture
def inductor_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "inductor"))


@pytest.mark.slow
@pytest.mark.parametrize("kwargs", [{"bc_alpha": 2.5}, {"maximiser": "sampled", "num_action_samples": 8}])
def test_compiled_losses_equal_eager_losses_on_a_fixed_batch(kwargs, inductor_cache, single_thread):
    torch.manual_seed(0)
    loss = WeightedBellmanLoss(make_q_network(3, 2, num_cells=(32, 32), activation="SiLU", initial_bias=40.0),
                               actor_network=make_deterministic_actor(3, SPEC, num_cells=(32,)), **kwargs)
    loss.make_value_estimator(gamma=0.9)
    twin = copy.deepcopy(loss)
    compiled = CompiledBellmanLosses(twin)
    batch = _batch()
    for _ in range(2):  # the second call runs the compiled code without compiling
        torch.manual_seed(1)
        value, figures = loss.value_loss(batch)
        torch.manual_seed(1)
        c_value, c_figures = compiled.value_loss(batch)
        torch.testing.assert_close(c_value, value, rtol=1e-5, atol=1e-5)
        assert set(c_figures) == set(figures)
        for key in figures:
            torch.testing.assert_close(c_figures[key], figures[key], rtol=1e-5, atol=1e-5)
        actor, a_figures = loss.actor_loss(batch)
        c_actor, c_a_figures = compiled.actor_loss(batch)
        torch.testing.assert_close(c_actor, actor, rtol=1e-5, atol=1e-5)
        assert set(c_a_figures) == set(a_figures)
        for a, b in ((value, c_value), (actor, c_actor)):
            loss.zero_grad(), twin.zero_grad()
            a.backward(), b.backward()
            for (name, p), (_, q) in zip(loss.named_parameters(), twin.named_parameters()):
                assert (p.grad is None) == (q.grad is None), name
                if p.grad is not None:
                    torch.testing.assert_close(q.grad, p.grad, rtol=1e-4, atol=1e-5)
    assert compiled.compile_seconds > 0


def test_compile_refuses_what_it_does_not_support():
    from torchrl_wbrm.modules import make_discrete_q_network

    discrete = WeightedBellmanLoss(make_discrete_q_network(3, 4, num_cells=(8,)))
    with pytest.raises(ValueError, match="continuous actions"):
        CompiledBellmanLosses(discrete)
    summed = WeightedBellmanLoss(make_q_network(3, 2, initial_bias=0.0, num_cells=(8,)), action_spec=SPEC, reduction="sum")
    with pytest.raises(ValueError, match="reduction"):
        CompiledBellmanLosses(summed)


@pytest.mark.slow
def test_trainer_with_q_compile_keeps_its_cache_in_the_run_directory(tmp_path, monkeypatch, single_thread):
    from tests.test_training import tiny_config
    from torchrl_wbrm.training import WBRMTrainer

    monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR", raising=False)
    run_dir = tmp_path / "run"
    results = WBRMTrainer(tiny_config(q={"compile": True}), run_dir, progress=False).run()
    assert results["compile_seconds"] > 0
    assert (run_dir / "torch_compile_cache").is_dir() and any((run_dir / "torch_compile_cache").iterdir())
    assert results["final"]["q_error_expert"] == results["final"]["q_error_expert"]  # a number (not NaN)


def test_q_compile_reaches_the_bellman_step():
    """q.compile=true gives the step compiled losses (building them compiles nothing yet: torch.compile is lazy)."""
    from torchrl_wbrm.training.algos import AlgoContext, build_algo
    from torchrl_wbrm.training.config import WBRMConfig, resolve_defaults

    for compile_, expected in ((True, CompiledBellmanLosses), (False, type(None))):
        cfg = resolve_defaults(WBRMConfig())  # the env's settings, as the trainer resolves them
        cfg.q.expert_bc_alpha = 0.0  # no task data here for the S^e cloning term
        cfg.q.compile = compile_
        cfg.q.num_cells = cfg.q.actor_num_cells = [8]
        algo = build_algo("wbrm", AlgoContext(cfg=cfg, observation_dim=3, action_dim=2, action_spec=SPEC, gamma=0.9,
                                              q_initial_bias=0.0))
        assert isinstance(algo.step.compiled, expected)
