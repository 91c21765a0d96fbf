"""``benchmarks/bench_seeds.py --update``: its vectorised update of several seeds takes each seed's own steps (no
timings are asserted)."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

ROOT = Path(__file__).resolve().parents[1]

#: a tiny LQR run (tests/test_seeds.py's), as recipe overrides
TINY = [
    "env.lqr_data.behaviour_episodes=40", "env.lqr_data.expert_episodes=20", "env.lqr_data.parallel_envs=20",
    "ratio.steps=10", "ratio.batch_size=64", "ratio.eval_every=10", "ratio.num_cells=[16,16]",
    "q.steps=40", "q.batch_size=32", "q.eval_every=20", "eval.offline_value=false", "eval.episodes=50",
    "eval.train_episodes=20", "eval.q_samples=300", "plots=false", "threads=1",
]


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_seeds", ROOT / "benchmarks" / "bench_seeds.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_the_vectorised_update_takes_each_seeds_own_steps(bench, tmp_path):
    """Two seeds' trainers after stage 1; four steps (two with the actor, its S^e draw from each seed's own generator
    state) of the vectorised update and of each seed's own ``algo.step`` on the same batches: the same losses at
    every step, and the same parameters and targets after them (up to the batched products' rounding)."""
    trainers = bench.trainers_after_stage1(8, [0, 1], TINY, tmp_path)
    update, stacked = bench.vectorised_update(trainers)
    for step in (1, 2, 3, 4):
        batches = [trainer.q_buffer.sample() for trainer in trainers]
        states = []
        for k in range(len(trainers)):
            torch.manual_seed(100 * step + k)
            states.append(torch.get_rng_state())
        together = update([batch.clone() for batch in batches], step, rng_states=states)
        for k, (trainer, batch) in enumerate(zip(trainers, batches)):
            torch.set_rng_state(states[k])
            alone = trainer.algo.step(batch.clone(), step)
            for key in ("loss_value", "loss_actor") if step % 2 == 0 else ("loss_value",):
                torch.testing.assert_close(together[key][k], alone[key], rtol=1e-4, atol=1e-5)
    for k, trainer in enumerate(trainers):
        own = TensorDict.from_module(trainer.algo.loss)
        for key, value in own.items(True, True):
            if value.device.type != "meta":
                torch.testing.assert_close(stacked[k][key], value, rtol=1e-4, atol=1e-5, msg=f"seed {k}: {key}")
    assert not torch.equal(stacked[0]["value_network_params"]["module", "0", "weight"],
                           stacked[1]["value_network_params"]["module", "0", "weight"])
