"""``LQREnv.rollout`` against a pure-torch loop of the same dynamics, at B = 1, 1024 and 16384, timed interleaved.

    python benchmarks/bench_env.py
    python benchmarks/bench_env.py --device cuda

Both run one 20-step episode (the env's horizon) of ``B`` systems under the same linear policy ``a = −Kx`` and
return every step's observation, action, reward and next observation: the env as the ``[B, 20]`` TensorDict of
``env.rollout`` (a fresh reset each call), the loop as stacked ``[B, 20, ·]`` tensors. Printed: steps/s
(``B · 20 / time``) and the median over rounds of the env's throughput over the loop's.
"""
from __future__ import annotations

import argparse
import os
import sys

import torch
from tensordict.nn import TensorDictModuleBase

sys.path.insert(0, os.path.dirname(__file__))
from _timing import compare, single_thread  # noqa: E402

from torchrl_wbrm.envs import LQREnv  # noqa: E402


class LinearPolicy(TensorDictModuleBase):
    """``a = −Kx`` written into the tensordict (a bare TensorDictModuleBase: no TensorDictModule wrapping cost)."""

    def __init__(self, K: torch.Tensor):
        super().__init__()
        self.in_keys, self.out_keys = ["observation"], ["action"]
        self.K = K

    def forward(self, tensordict):
        return tensordict.set("action", -tensordict.get("observation") @ self.K.T)


def pure_torch_rollout(env: LQREnv, K: torch.Tensor, g: torch.Generator):
    cfg, B, d = env.config, env.batch_size[0], env.config.state_dim
    dev, dt = env.device, env._dtype
    F, G, R, S = env._F, env._G, env._R, env._S
    x = cfg.initial_std * torch.randn(B, d, generator=g, device=dev, dtype=dt)
    obs, act, rew, nxt = [], [], [], []
    for _ in range(cfg.horizon):
        a = -x @ K.T
        cost = ((x @ S) * x).sum(-1, keepdim=True) + ((a @ R) * a).sum(-1, keepdim=True)
        r = (cfg.reward_offset - cost + cfg.reward_noise_std * torch.randn(B, 1, generator=g, device=dev, dtype=dt))
        r = r.clamp_min(cfg.reward_clip)
        x_next = x @ F.T + a @ G.T + cfg.transition_noise_std * torch.randn(B, d, generator=g, device=dev, dtype=dt)
        obs.append(x), act.append(a), rew.append(r), nxt.append(x_next)
        x = x_next
    return [torch.stack(v, 1) for v in (obs, act, rew, nxt)]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 1024, 16384])
    parser.add_argument("--rounds", type=int, default=7)
    args = parser.parse_args(argv)
    single_thread()
    device = torch.device(args.device)
    sync = torch.cuda.synchronize if device.type == "cuda" else None
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), device {device}")
    print("\nLQREnv.rollout (one 20-step episode of B systems, policy a = -Kx) vs a pure-torch loop "
          "(ratio: env throughput / loop throughput, median over rounds)")
    for B in args.sizes:
        env = LQREnv("exp1", batch_size=[B], device=device, seed=0)
        K = env.riccati()[1].to(device=device, dtype=torch.float32)
        g = torch.Generator(device=device).manual_seed(0)

        policy = LinearPolicy(K)

        iterations = max(3, min(50, 400_000 // (B * 20) + 1))
        out = compare(
            {"pure torch": lambda: pure_torch_rollout(env, K, g), "LQREnv.rollout": lambda: env.rollout(20, policy)},
            yardstick="pure torch", iterations=iterations, rounds=args.rounds, warmup=3, sync=sync,
        )
        steps = B * 20
        loop, ours = out["pure torch"], out["LQREnv.rollout"]
        print(f"  B = {B:>6}: pure torch {steps / loop['median_s'] / 1e6:7.3f} M steps/s, LQREnv.rollout "
              f"{steps / ours['median_s'] / 1e6:7.3f} M steps/s   ratio {1 / ours['ratio']:.2f}x")


if __name__ == "__main__":
    main()
