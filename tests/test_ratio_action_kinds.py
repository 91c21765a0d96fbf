"""Stage 1 on any action kind: categorical index actions (one-hot inside the fitted network), multi-dimensional
sets flattened, multi-dimensional storages refused in one line, and the tiny-ESS warning of store_density_ratio."""
from __future__ import annotations

import warnings

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_wbrm.ratio import fit_density_ratio, store_density_ratio


def _categorical(n: int, expert: bool, seed: int, keepdim: bool = False) -> TensorDict:
    """x ~ N(0, 1); the behaviour picks one of 3 actions uniformly, the expert picks 2 where x > 0 and 0 elsewhere."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, 1, generator=g)
    action = torch.where(x[:, 0] > 0, 2, 0) if expert else torch.randint(0, 3, (n,), generator=g)
    return TensorDict({"observation": x, "action": action.unsqueeze(-1) if keepdim else action}, [n])


@pytest.mark.slow
@pytest.mark.parametrize("keepdim", [False, True])
def test_fit_and_store_take_categorical_index_actions(keepdim):
    """Index actions [N] (or [N, 1]) are one-hot inside the fitted network (sized 1 + 3 inputs, not N): ŵ is large
    on the expert's (x, a) pairs and small on the actions it never takes, and store_density_ratio runs the network on
    the buffer's own index actions."""
    behaviour, expert = _categorical(1000, False, 0, keepdim), _categorical(500, True, 1, keepdim)
    fit = fit_density_ratio(behaviour, expert, steps=120, eval_every=40, batch_size=128, num_cells=(16,), lr=1e-2)
    assert not fit.ratio_collapse
    w = fit.network(expert.clone())["density_ratio"]
    assert w.mean() > 2.0  # the true ratio is 3 on the expert's pairs
    never = behaviour.clone()
    never["action"] = torch.where(behaviour["observation"] > 0, 0, 2).reshape(behaviour["action"].shape)
    assert fit.network(never)["density_ratio"].mean() < 0.5  # and 0 on the pairs it never takes
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(1000), batch_size=16)
    rb.extend(behaviour)
    stored = store_density_ratio(rb, ratio_network=fit.network, temper=1.0)
    assert stored.shape == (1000,) and rb.sample()["density_ratio"].shape == (16,)
    with pytest.raises(ValueError, match=r"indices run from 0 to 2, outside \[0, 1\] for num_actions=2"):
        fit_density_ratio(behaviour, expert, steps=1, num_actions=2)


def test_multi_dimensional_sets_are_flattened_and_storages_refused():
    """[episodes, steps] TensorDicts are read one row per sample (fit and store: the stored weights keep the
    TensorDict's shape, equal to the flat rows'); a 2-d storage is refused in one line."""
    behaviour, expert = _categorical(400, False, 0), _categorical(200, True, 1)
    fit = fit_density_ratio(behaviour.reshape(20, 20), expert.reshape(10, 20), steps=20, eval_every=10,
                            batch_size=64, num_cells=(8,))
    grid = behaviour.reshape(20, 20)
    stored = store_density_ratio(grid, ratio_network=fit.network)
    assert stored.shape == (20, 20) and grid["density_ratio"].shape == (20, 20)
    torch.testing.assert_close(stored.reshape(-1), store_density_ratio(behaviour.clone(), ratio_network=fit.network))
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(20, ndim=2), batch_size=4)
    rb.extend(grid)
    with pytest.raises(ValueError, match="needs a 1-d storage .* got a 2-d LazyTensorStorage"):
        store_density_ratio(rb, torch.ones(400))


def test_store_warns_when_the_effective_sample_size_is_tiny_naming_ratio_temper():
    rows = TensorDict({"observation": torch.randn(1000, 1)}, [1000])
    spiky = torch.ones(1000)
    spiky[0] = 1e6
    with pytest.warns(UserWarning, match=r"effective sample size .* of 1\.0 for 1000 rows.*ratio\.temper"):
        store_density_ratio(rows, spiky)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        store_density_ratio(rows, spiky, temper=0.25)  # tempered: ESS well above 1%
        store_density_ratio(rows, torch.rand(1000) + 0.5)
