"""``make_lqr_env``: the LQR system with torchrl's own transforms composed on top.

Nothing here re-implements a transform: ``StepCounter`` records the time index ``t`` of every transition
(``"step_count"``, used to check per-step laws and the occupancy mixture), ``ObservationNorm`` standardises
observations when asked, ``ActionDiscretizer`` turns the continuous action box into a categorical grid for the
discrete-action (DQN) baseline, and ``DoubleToFloat`` is not needed because the env is float32 already.
"""
from __future__ import annotations

from typing import Sequence

import torch
from torchrl.envs import ActionDiscretizer, Compose, ObservationNorm, StepCounter, TransformedEnv

from torchrl_wbrm.envs.lqr import LQRConfig, LQREnv

__all__ = ["make_lqr_env"]


def make_lqr_env(
    experiment: str | LQRConfig = "exp1",
    *,
    batch_size: int | Sequence[int] = (),
    seed: int | None = None,
    device: torch.device | str | None = None,
    step_counter: bool = True,
    observation_norm: bool | tuple[float, float] = False,
    discretize_actions: int | None = None,
) -> TransformedEnv:
    """Build an :class:`LQREnv` wrapped in torchrl transforms.

    Args:
        experiment: ``"exp1" | "exp2" | "exp3"`` or an :class:`LQRConfig`.

    Keyword Args:
        batch_size: number of systems stepped in parallel.
        seed: the env's seed.
        device: torch device.
        step_counter: append ``StepCounter`` (writes ``"step_count"``; the env truncates on its own).
        observation_norm: ``False`` (off), ``True`` (standardise with the exact stationary law of ``x_0``:
            loc 0, scale ``initial_std``) or an explicit ``(loc, scale)`` pair.
        discretize_actions: if an int ``n``, append ``ActionDiscretizer(n)``: each action coordinate takes
            ``n`` evenly spaced values (bin medians) in the action bound; the action becomes a
            ``MultiCategorical`` with one categorical of ``n`` values per coordinate.

    Examples:
        >>> env = make_lqr_env("exp2", batch_size=[8], seed=0, discretize_actions=5)
        >>> env.action_spec.shape
        torch.Size([8, 2])
    """
    base = LQREnv(experiment, batch_size=batch_size, device=device, seed=seed)
    transforms = []
    if step_counter:
        transforms.append(StepCounter())
    if observation_norm is not False:
        if observation_norm is True:
            loc, scale = 0.0, base.config.initial_std
        else:
            try:
                loc, scale = observation_norm
            except (TypeError, ValueError):
                raise ValueError(
                    f"observation_norm must be False, True or a (loc, scale) pair, got {observation_norm!r}."
                ) from None
        if scale <= 0:
            raise ValueError(f"observation_norm scale must be > 0, got {scale}.")
        transforms.append(ObservationNorm(loc=loc, scale=scale, in_keys=["observation"], standard_normal=True))
    if discretize_actions is not None:
        if int(discretize_actions) != discretize_actions or discretize_actions < 2:
            raise ValueError(f"discretize_actions must be an integer >= 2, got {discretize_actions!r}.")
        transforms.append(
            ActionDiscretizer(
                int(discretize_actions),
                categorical=True,
                sampling=ActionDiscretizer.SamplingStrategy.MEDIAN,
            )
        )
    return TransformedEnv(base, Compose(*transforms))
