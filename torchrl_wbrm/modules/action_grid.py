"""The joint action grid of a discretised action box, for a DQN head over continuous actions (``algo=dqn``)."""
from __future__ import annotations

import torch
from torch import nn
from torchrl.envs import ActionDiscretizer, Compose, TransformedEnv

from torchrl_wbrm.envs import make_lqr_env

__all__ = ["ActionGrid"]


class ActionGrid(nn.Module):
    """The joint action grid of a discretised box: ``num_bins`` values per coordinate, ``num_bins ** m`` actions.

    The values are those of torchrl's ``ActionDiscretizer`` (bin medians) on the LQR env
    (``make_lqr_env(..., discretize_actions=num_bins)``), read from the transform, so the grid is the env's own.
    That transform yields one categorical per coordinate (a ``MultiCategorical``); a DQN head needs one categorical
    over the joint actions, indexed ``k = Σ_j i_j · n^(m−1−j)`` (coordinate 0 most significant).

    ``index(action)`` snaps continuous actions to the nearest grid point per coordinate and returns the joint index
    (the dataset's actions -> DQN's); ``forward(index)`` returns the continuous action of a joint index (DQN's greedy
    action -> the env): indices of shape ``[*B]`` give actions of shape ``[*B, m]``.
    """

    def __init__(self, values: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("values", values)  # [m, n]
        m, n = values.shape
        self.register_buffer("radix", n ** torch.arange(m - 1, -1, -1))

    @classmethod
    def from_lqr_env(cls, lqr_config, num_bins: int) -> "ActionGrid":
        return cls.from_env(make_lqr_env(lqr_config).base_env, num_bins)

    @classmethod
    def from_env(cls, env, num_bins: int) -> "ActionGrid":
        """The grid of torchrl's ``ActionDiscretizer(num_bins)`` (bin medians) on ``env``'s bounded action spec."""
        discretised = TransformedEnv(env, ActionDiscretizer(int(num_bins), categorical=True,
                                                            sampling=ActionDiscretizer.SamplingStrategy.MEDIAN))
        _ = discretised.action_spec  # the transform builds its grid from the parent's spec
        transform = discretised.transform
        transform = transform[-1] if isinstance(transform, Compose) else transform
        return cls(transform.intervals.detach().clone().float().reshape(-1, int(num_bins)))

    @property
    def num_actions(self) -> int:
        return int(self.values.shape[1] ** self.values.shape[0])

    def index(self, action: torch.Tensor) -> torch.Tensor:
        per_coordinate = (action.unsqueeze(-1) - self.values).abs().argmin(-1)  # [*B, m]
        return (per_coordinate * self.radix).sum(-1)

    def forward(self, index: torch.Tensor) -> torch.Tensor:
        # ``index`` is categorical, of shape [*B] (torchrl's ``QValueModule`` with ``action_space="categorical"``):
        # no trailing dimension to squeeze, so a batch of one ([1]) stays a batch of one
        per_coordinate = (index.unsqueeze(-1) // self.radix) % self.values.shape[1]  # [*B, m]
        return torch.gather(self.values.expand(*per_coordinate.shape[:-1], *self.values.shape), -1,
                            per_coordinate.unsqueeze(-1)).squeeze(-1)
