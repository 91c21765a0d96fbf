"""Expert and behaviour policies for the LQR system, as TensorDictModules a torchrl ``Collector`` can run.

Both are linear-Gaussian, ``a = -M x + sigma * N(0, I)``, so their state-action laws are Gaussian at every step
and the true density ratio between them is known (:func:`lqr_true_density_ratio`).

Expert (Section 5.1, Eq. "pi^e = (1 - tau) pi* + tau eps_t", tau = 0.05). We read the equation as a convex
combination of *actions*: ``a = (1 - tau) (-K x) + tau eps``, ``eps ~ N(0, I)``, i.e. gain ``(1 - tau) K`` and
noise standard deviation ``tau``. This is the same reading the paper's MountainCar expert needs
(``0.9 sign(v) + 0.1 U(-1, 1)``). The other reading, a mixture that acts randomly with probability ``tau``,
would not give a Gaussian law; the gain scale and noise are configurable for anyone who wants another expert.

Behaviour. The paper does not give one. Default: ``a = -0.5 K x + N(0, 0.5^2 I)``: half the optimal gain and
ten times the expert's noise, a poorer, noisier policy whose Gaussian support covers the expert's (every
linear-Gaussian policy with positive noise does). Its exact discounted 20-step return (unclipped reward) is
83.11 on exp1, 83.68 on exp2 and 84.05 on exp3, against 85.39 / 85.27 / 85.12 for the expert (``policy_return``;
``python recipes/policy_returns.py`` measures the same within its 95% CI).

Under ``set_exploration_type(DETERMINISTIC)`` the policies return their mean action ``-M x`` (as torchrl's
exploration modules do); collectors run in ``RANDOM`` mode and add the noise.
"""
from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType, exploration_type

from torchrl_wbrm.keys import DENSITY_RATIO
from torchrl_wbrm.envs.lqr import LinearGaussianDensityRatio, LQREnv

__all__ = [
    "LinearGaussianPolicy",
    "make_lqr_expert",
    "make_lqr_behaviour",
    "make_lqr_optimal_policy",
    "lqr_true_density_ratio",
]


class LinearGaussianPolicy(nn.Module):
    """``a = -M x + sigma * N(0, I)`` with a fixed gain ``M`` (``m x d``) and noise std ``sigma``.

    Args:
        gain: the matrix ``M``.
        noise_std: ``sigma`` (``>= 0``).

    Keyword Args:
        generator (torch.Generator, optional): the noise's generator (defaults to torch's global one, so
            ``torch.manual_seed`` makes collection reproducible).
    """

    def __init__(self, gain: torch.Tensor, noise_std: float, *, generator: torch.Generator | None = None):
        super().__init__()
        gain = torch.as_tensor(gain, dtype=torch.float32)
        if gain.ndim != 2:
            raise ValueError(f"gain must be an (action_dim, state_dim) matrix, got shape {tuple(gain.shape)}.")
        if noise_std < 0:
            raise ValueError(f"noise_std must be >= 0, got {noise_std}.")
        self.register_buffer("gain", gain)
        self.noise_std = float(noise_std)
        self.generator = generator

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        mean = -observation @ self.gain.T
        if self.noise_std == 0 or exploration_type() in (ExplorationType.DETERMINISTIC, ExplorationType.MODE):
            return mean
        noise = torch.randn(mean.shape, generator=self.generator, device=mean.device, dtype=mean.dtype)
        return mean + self.noise_std * noise

    def extra_repr(self) -> str:
        return f"gain={self.gain.tolist()}, noise_std={self.noise_std}"


def _as_module(policy: LinearGaussianPolicy) -> TensorDictModule:
    return TensorDictModule(policy, in_keys=["observation"], out_keys=["action"])


def _base(env) -> LQREnv:
    while not isinstance(env, LQREnv):
        if not hasattr(env, "base_env"):
            raise TypeError(f"Expected an LQREnv (possibly transformed), got {type(env).__name__}.")
        env = env.base_env
    return env


def make_lqr_optimal_policy(env) -> TensorDictModule:
    """The stationary optimal policy ``a = -K x`` (deterministic)."""
    _, K = _base(env).riccati()
    return _as_module(LinearGaussianPolicy(K, 0.0))


def make_lqr_expert(env, *, tau: float = 0.05, generator: torch.Generator | None = None) -> TensorDictModule:
    """The paper's expert ``a = (1 - tau)(-K x) + tau N(0, I)`` (see the module docstring for the reading)."""
    if not 0.0 <= tau < 1.0:
        raise ValueError(f"tau must lie in [0, 1), got {tau}.")
    _, K = _base(env).riccati()
    return _as_module(LinearGaussianPolicy((1.0 - tau) * K, tau, generator=generator))


def make_lqr_behaviour(
    env, *, gain_scale: float = 0.5, noise_std: float = 0.5, generator: torch.Generator | None = None
) -> TensorDictModule:
    """The behaviour policy ``a = -gain_scale K x + N(0, noise_std^2 I)`` (default: 0.5 and 0.5)."""
    if noise_std <= 0:
        raise ValueError(
            f"The behaviour policy needs noise_std > 0 so that its support covers the expert's, got {noise_std}."
        )
    _, K = _base(env).riccati()
    return _as_module(LinearGaussianPolicy(gain_scale * K, noise_std, generator=generator))


def lqr_true_density_ratio(
    env, expert: TensorDictModule, behaviour: TensorDictModule, *, time_weights: str = "uniform",
    behaviour_initial_std: float | None = None,
) -> TensorDictModule:
    """The exact ratio ``d P^e / d P^b`` of the two policies' occupancies, as a module writing ``"density_ratio"``.

    ``time_weights="uniform"`` (default) mixes the per-step laws over ``t = 0..horizon-1`` with equal weights,
    which is how the datasets of :mod:`torchrl_wbrm.data` sample transitions (every step of every episode once).
    ``behaviour_initial_std``: the behaviour episodes start from ``N(0, behaviour_initial_std^2 I)`` (``None``: the
    system's ``initial_std``, as the expert's do).
    """
    e, b = expert.module, behaviour.module
    if not (isinstance(e, LinearGaussianPolicy) and isinstance(b, LinearGaussianPolicy)):
        raise TypeError("lqr_true_density_ratio needs two LinearGaussianPolicy modules (see make_lqr_expert).")
    ratio = LinearGaussianDensityRatio(
        _base(env), e.gain, e.noise_std, b.gain, b.noise_std, time_weights=time_weights,
        behaviour_initial_std=behaviour_initial_std,
    )
    return TensorDictModule(ratio, in_keys=["observation", "action"], out_keys=[DENSITY_RATIO])
