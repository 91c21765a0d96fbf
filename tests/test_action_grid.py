"""torchrl_wbrm.modules.action_grid: ActionGrid, the joint grid of a discretised action box (algo=dqn's action
space)."""
from __future__ import annotations

import torch

from torchrl_wbrm.modules import ActionGrid


def test_grid_round_trip_and_snapping():
    grid = ActionGrid.from_lqr_env("exp1", 5)
    assert grid.num_actions == 25 and grid.values.shape == (2, 5)
    index = torch.arange(grid.num_actions)
    actions = grid(index)
    assert torch.equal(grid.index(actions), index)  # every grid point maps back to its own index
    nudged = actions + 0.1 * (grid.values[0, 1] - grid.values[0, 0])  # a tenth of a bin off: snaps back
    assert torch.equal(grid.index(nudged), index)
    assert torch.equal(grid.values[0], grid.values[1])  # the box is the same in both coordinates
    assert grid.values[0, 2].abs() < 1e-6 and (grid.values[0].diff() > 0).all()  # symmetric bins, in order

