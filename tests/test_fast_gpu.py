"""device=cuda: the hot paths run on the device with no per-step host sync. Marked ``gpu``: skipped without CUDA."""
from __future__ import annotations

import pytest
import torch

from torchrl_wbrm.data import make_replay_buffer
from torchrl_wbrm.data.sampling import BufferBatches, PairedSampler

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
]


def _data(n=512):
    from tests.test_fast import _data as data

    return data(n)


def _no_sync():
    """Raise on any synchronising CUDA call inside the block (torch's sync debug mode)."""
    class _Guard:
        def __enter__(self):
            torch.cuda.synchronize()
            self.mode = torch.cuda.get_sync_debug_mode()
            torch.cuda.set_sync_debug_mode("error")

        def __exit__(self, *exc):
            torch.cuda.set_sync_debug_mode(self.mode)

    return _Guard()


def test_buffer_batches_on_cuda_draw_and_gather_without_a_sync():
    batches = BufferBatches(make_replay_buffer(_data(), batch_size=64), device="cuda")
    batches.sample()
    with _no_sync():
        for _ in range(3):
            batch = batches.sample()
    assert batch.device.type == "cuda" and batch["observation"].device.type == "cuda"
    paired = PairedSampler(make_replay_buffer(_data()), make_replay_buffer(_data(200)), 32, device="cuda")
    with _no_sync():
        pair = paired.sample()
    assert pair["expert", "action"].device.type == "cuda"


def test_wbrm_update_on_cuda_without_a_sync():
    from torchrl.data import Bounded

    from torchrl_wbrm.algos import AlgoContext, build_algo
    from torchrl_wbrm.training.config import WBRMConfig

    cfg = WBRMConfig()
    cfg.q.num_cells = cfg.q.actor_num_cells = [32, 32]
    ctx = AlgoContext(cfg=cfg, observation_dim=3, action_dim=2, action_spec=Bounded(-2.0, 2.0, (2,), device="cuda"),
                      gamma=0.9, q_initial_bias=10.0, device=torch.device("cuda"))
    algo = build_algo("wbrm", ctx)
    batches = BufferBatches(make_replay_buffer(_data(), batch_size=64), device="cuda")
    algo.step(batches.sample(), 1), algo.step(batches.sample(), 2)  # warm-up (lazy CUDA init, optimiser state)
    with _no_sync():
        for i in range(3, 7):
            figures = algo.step(batches.sample(), i)
    assert all(v.device.type == "cuda" for v in figures.values())


def test_lqr_rollout_on_cuda_equals_torchrl_rollout():
    from torchrl.envs import EnvBase

    from tests.test_fast import _NoisyLinearPolicy
    from torchrl_wbrm.envs import LQREnv

    envs = [LQREnv("exp1", batch_size=[64], device="cuda", seed=0) for _ in range(2)]
    policy = _NoisyLinearPolicy(envs[0].riccati()[1].float().cuda())
    outs = []
    for env, rollout in zip(envs, (LQREnv.rollout, EnvBase.rollout)):
        torch.manual_seed(0)
        outs.append(rollout(env, 20, policy))
    assert all(torch.equal(outs[0].get(k), outs[1].get(k)) for k in outs[1].keys(True, True))


def test_trainer_runs_on_cuda(tmp_path):
    from torchrl_wbrm.training import WBRMTrainer
    from torchrl_wbrm.training.config import WBRMConfig

    cfg = WBRMConfig(device="cuda", plots=False)
    cfg.env.lqr_data.behaviour_episodes, cfg.env.lqr_data.expert_episodes = 100, 50
    cfg.ratio.steps, cfg.q.steps, cfg.q.eval_every, cfg.ratio.eval_every = 20, 20, 20, 10
    cfg.eval.episodes = cfg.eval.train_episodes = 100
    cfg.eval.q_samples = 500
    results = WBRMTrainer(cfg, tmp_path / "run", progress=False).run()
    assert results["final"]


def test_trainer_divergence_check_on_cuda_reads_the_device_only_on_check_steps(tmp_path):
    from torchrl_wbrm.training import WBRMTrainer
    from torchrl_wbrm.training.config import WBRMConfig

    cfg = WBRMConfig(device="cuda", plots=False)
    cfg.env.lqr_data.behaviour_episodes, cfg.env.lqr_data.expert_episodes = 100, 50
    cfg.eval.q_samples = 500
    trainer = WBRMTrainer(cfg, tmp_path / "run", progress=False)
    good = {"loss": torch.tensor(1.0, device="cuda")}
    bad = {"loss": torch.tensor(float("nan"), device="cuda")}
    with _no_sync():
        assert trainer.finite_watch(good, read=False) is None
        assert trainer.finite_watch(bad, read=False) is None  # not read yet
    assert trainer.finite_watch(good, read=True) is not None  # the window held a NaN
    assert trainer.finite_watch(good, read=True) is None



def _not_on(trainer, device_type: str) -> list[str]:
    """The trained loss's parameters and buffers (its networks and the fixed maps inside them) not on ``device_type``."""
    loss = trainer.q_loss
    return [name for name, t in (*loss.named_parameters(), *loss.named_buffers()) if t.device.type != device_type]


@pytest.mark.parametrize("algo", ["wbrm", "bc", "brm", "cql", "ddpg", "dqn", "fqi", "iql", "mabo", "td3bc"])
def test_each_algo_trains_on_cuda_and_resumes_as_the_uninterrupted_run(tmp_path, algo):
    """Every algo's networks, the unit-action maps of TD3+BC, IQL and CQL and the evaluated policy live on the device,
    and a run cut on the device resumes from its checkpoint to the uninterrupted run's results (the CUDA generator,
    which draws the batches and the losses' noise there, is in the checkpoint)."""
    from torchrl_wbrm.algos import ALGOS
    from torchrl_wbrm.training import WBRMTrainer

    from tests.test_training import tiny_config

    assert algo in ALGOS
    cfg = tiny_config(algo=algo, device="cuda")
    whole = WBRMTrainer(cfg, tmp_path / "whole", progress=False)
    results = whole.run()
    assert results["final"]["return"] == results["final"]["return"]  # present and not NaN
    assert _not_on(whole, "cuda") == []
    cut = WBRMTrainer(cfg, tmp_path / "cut", progress=False)
    assert cut.run(until=15) is None
    resumed = WBRMTrainer(cfg, tmp_path / "cut", progress=False, resume=True).run()
    assert resumed["final"] == results["final"]


def test_seeds_in_one_process_on_cuda(tmp_path):
    from torchrl_wbrm.training.seeds import run_seeds

    from tests.test_training import tiny_config

    out = run_seeds(tiny_config(algo="wbrm", device="cuda", seeds=[0, 1]), tmp_path / "run", progress=False)
    assert len(out["runs"]) == 2 and all(r["final"]["return"] == r["final"]["return"] for r in out["runs"])


@pytest.mark.parametrize("where", ["gym", "lqr"])
def test_a_policy_on_cuda_is_evaluated_in_an_env_on_the_cpu(where):
    """The evaluators' envs step on the CPU (a gym env; the LQR env they build): a policy trained on the device
    acts there through torchrl's rollout cast, with the returns of the same policy on the CPU."""
    from tensordict.nn import TensorDictModule
    from torch import nn

    from torchrl_wbrm.evaluation.metrics import evaluate_returns, lqr_paired_regret

    torch.manual_seed(0)
    if where == "gym":
        from torchrl.envs import DoubleToFloat, GymEnv, TransformedEnv

        env = TransformedEnv(GymEnv("Pendulum-v1", device="cpu"), DoubleToFloat())
        net = nn.Sequential(nn.Linear(3, 1), nn.Tanh())
        score = lambda policy: evaluate_returns(env, policy, episodes=2, seed=0, max_steps=50).mean  # noqa: E731
    else:
        net = nn.Linear(2, 2)
        score = lambda policy: lqr_paired_regret("exp1", policy, episodes=20, seed=0)["regret"].mean  # noqa: E731
    on_cpu = score(TensorDictModule(net, in_keys=["observation"], out_keys=["action"]))
    on_cuda = score(TensorDictModule(net.cuda(), in_keys=["observation"], out_keys=["action"]))
    assert on_cuda == pytest.approx(on_cpu, rel=1e-4, abs=1e-4)
