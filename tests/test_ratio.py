"""Stage 1 as a library (torchrl_wbrm.ratio): fit ŵ from two datasets or replay buffers with held-out early stopping,
compute it over a dataset in chunks, shape it and store it in a replay buffer's storage; the trainer uses the same
pieces."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer

from torchrl_wbrm.modules import DensityRatioNetwork
from torchrl_wbrm.objectives import RobustDensityRatioLoss
from torchrl_wbrm.ratio import (
    DensityRatioFitter,
    NonFiniteWeightsError,
    compute_density_ratio,
    fit_density_ratio,
    holdout_split,
    shape_weights,
    store_density_ratio,
)

EXPERT_STD, BEHAVIOUR_STD = 0.3, 1.0


def _samples(n: int, std: float, seed: int) -> TensorDict:
    """x ~ N(0, 1), a = −x + N(0, std²): the ratio of two such sets is N(a; −x, 0.3²) / N(a; −x, 1)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, 1, generator=g)
    return TensorDict({"observation": x, "action": -x + std * torch.randn(n, 1, generator=g)}, [n])


def _true_ratio(td: TensorDict) -> torch.Tensor:
    z = (td["action"] + td["observation"]).reshape(-1).double()
    e, b = torch.distributions.Normal(0.0, EXPERT_STD), torch.distributions.Normal(0.0, BEHAVIOUR_STD)
    return (e.log_prob(z) - b.log_prob(z)).exp()


def _buffer(td: TensorDict, storage=LazyTensorStorage) -> TensorDictReplayBuffer:
    rb = TensorDictReplayBuffer(storage=storage(td.shape[0]), batch_size=32)
    rb.extend(td)
    return rb


@pytest.fixture(scope="module")
def gaussian_fit():
    torch.manual_seed(0)
    behaviour, expert = _samples(4000, BEHAVIOUR_STD, 1), _samples(2000, EXPERT_STD, 2)
    network = DensityRatioNetwork(1, 1, bounds=(1e-3, 1e2), num_cells=(32, 32))
    fit = fit_density_ratio(behaviour, expert, network, steps=600, eval_every=25, patience=100, batch_size=256,
                            lr=3e-3, seed=0)
    return fit, behaviour


def test_fit_recovers_a_known_ratio(gaussian_fit):
    """Against the exact ratio of two Gaussians on fresh behaviour samples: small relative L2 error, mean ≈ 1 under
    the behaviour law, and far better than ŵ ≡ 1."""
    fit, _ = gaussian_fit
    fresh = _samples(20_000, BEHAVIOUR_STD, 3)
    with torch.no_grad():
        w_hat = fit.network(fresh.clone())["density_ratio"].reshape(-1).double()
    w = _true_ratio(fresh)
    error = ((w_hat - w).pow(2).mean().sqrt() / w.pow(2).mean().sqrt()).item()
    constant = ((1 - w).pow(2).mean().sqrt() / w.pow(2).mean().sqrt()).item()
    assert error < 0.35 and error < constant / 2, (error, constant)
    assert w_hat.mean().item() == pytest.approx(1.0, abs=0.15)
    assert fit.diagnostics["held_out_loss"] == pytest.approx(fit.best_loss, abs=1e-6)
    assert fit.best_loss < 1 - (1 + 1 / 0.5)  # below the loss of ŵ ≡ 1
    assert {"density_ratio_behaviour_mean", "density_ratio_expert_mean", "density_ratio_ess"} <= fit.diagnostics.keys()
    assert [r["step"] for r in fit.history] == list(range(25, 601, 25)) and fit.steps_run == 600


def test_early_stopping_restores_the_best_held_out_state():
    """With a learning rate that overfits and a short patience the fit stops early and returns the network of its
    best evaluation (recomputed here), not its last."""
    torch.manual_seed(0)
    behaviour, expert = _samples(300, BEHAVIOUR_STD, 1), _samples(150, EXPERT_STD, 2)
    network = DensityRatioNetwork(1, 1, num_cells=(64, 64))
    fitter = DensityRatioFitter(network, behaviour, expert, batch_size=64, lr=0.05, patience=2,
                                holdout_fraction=0.3)
    fit = fitter.fit(steps=2000, eval_every=5)
    assert fit.stopped_early and fit.steps_run < 2000
    losses = [r["held_out_loss"] for r in fit.history]
    assert min(losses) == pytest.approx(fit.best_loss) and losses[-1] > fit.best_loss + 1e-4
    assert fit.history[losses.index(min(losses))]["step"] == fit.best_step
    with torch.no_grad():
        now = fitter.loss_module(fitter.holdout)["loss_density_ratio"].item()
    assert now == pytest.approx(fit.best_loss, abs=1e-6)


def test_buffers_and_tensordicts_give_the_same_fit():
    behaviour, expert = _samples(400, BEHAVIOUR_STD, 1), _samples(200, EXPERT_STD, 2)

    def run(b, e):
        torch.manual_seed(0)
        fit = fit_density_ratio(b, e, steps=30, eval_every=10, batch_size=32, num_cells=(16,), seed=5)
        return fit.network.state_dict(), fit.best_loss

    (sd_a, loss_a), (sd_b, loss_b) = run(behaviour, expert), run(_buffer(behaviour), _buffer(expert))
    assert loss_a == loss_b and all(torch.equal(sd_a[k], sd_b[k]) for k in sd_a)


def test_state_dict_resumes_bit_identically():
    """20 + 20 steps with a state_dict save/load in between (and the global RNG restored) end where 40 steps do."""
    behaviour, expert = _samples(400, BEHAVIOUR_STD, 1), _samples(200, EXPERT_STD, 2)

    def fitter():
        torch.manual_seed(0)
        return DensityRatioFitter(DensityRatioNetwork(1, 1, num_cells=(16,)), behaviour, expert, batch_size=32,
                                  generator=torch.Generator().manual_seed(1))

    full = fitter()
    full.fit(steps=40, eval_every=10)
    first = fitter()
    first.fit(steps=20, eval_every=10)
    state, rng = first.state_dict(), torch.get_rng_state()
    second = fitter()
    second.load_state_dict(state)
    torch.set_rng_state(rng)
    second.fit(steps=40, eval_every=10)
    a, b = full.network.state_dict(), second.network.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert full.best["loss"] == second.best["loss"] and full.best["step"] == second.best["step"]
    assert second.num_steps == 40


def test_holdout_split_is_disjoint_and_seeded():
    td = TensorDict({"x": torch.arange(100)}, [100])
    train, held = holdout_split(td, 0.1, torch.Generator().manual_seed(3))
    assert held.shape == (10,) and train.shape == (90,)
    assert set(train["x"].tolist()).isdisjoint(held["x"].tolist())
    again = holdout_split(td, 0.1, torch.Generator().manual_seed(3))[1]
    assert torch.equal(again["x"], held["x"])
    with pytest.raises(ValueError, match="fraction"):
        holdout_split(td, 1.0)


def test_compute_density_ratio_in_chunks_equals_one_pass():
    torch.manual_seed(0)
    net = DensityRatioNetwork(1, 1, num_cells=(8,))
    data = _samples(1000, BEHAVIOUR_STD, 4)
    with torch.no_grad():
        whole = net(data.select("observation", "action"))["density_ratio"]
    chunked = compute_density_ratio(net, _buffer(data), chunk_size=77)
    assert chunked.shape == (1000, 1)
    torch.testing.assert_close(chunked, whole)


@pytest.mark.parametrize("storage", [LazyTensorStorage, LazyMemmapStorage])
@pytest.mark.parametrize("key", ["density_ratio", "priority_weight"])
def test_store_in_a_replay_buffer_under_a_chosen_key_with_shaping(storage, key):
    """The shaped weights land in the buffer's storage row by row (every sample carries its own), default shape [N]."""
    torch.manual_seed(0)
    net = DensityRatioNetwork(1, 1, num_cells=(8,))
    with torch.no_grad():
        net.module.mlp[-1].weight.mul_(30.0)  # a spread-out ratio, so that the shaping matters
    data = _samples(200, BEHAVIOUR_STD, 5)
    data["row"] = torch.arange(200)
    if storage is LazyMemmapStorage:  # a locked storage takes no new entry: the data hold it from the first extend
        data[key] = torch.zeros(200)
    rb = _buffer(data, storage)
    stored = store_density_ratio(rb, ratio_network=net, key=key, temper=0.5, clip=3.0, mix=0.1)
    raw = compute_density_ratio(net, data)
    expected = shape_weights(raw, temper=0.5, clip=3.0, mix=0.1).reshape(-1)
    torch.testing.assert_close(stored, expected)
    assert stored.shape == (200,) and stored.mean().item() == pytest.approx(1.0, rel=1e-5)
    batch = rb.sample()
    torch.testing.assert_close(batch[key], expected[batch["row"]])
    again = store_density_ratio(rb, torch.ones(200), key=key)  # an existing entry is overwritten in place
    assert (rb[:][key] == 1).all() and again.shape == (200,)


def test_store_in_a_tensordict_keepdim_dtype_and_errors():
    td = _samples(4, BEHAVIOUR_STD, 6)
    stored = store_density_ratio(td, torch.tensor([1.0, 2.0, 3.0, 2.0], dtype=torch.float64), keepdim=True,
                                 dtype=torch.float32)
    assert td["density_ratio"].shape == (4, 1) and td["density_ratio"].dtype == torch.float32
    torch.testing.assert_close(stored, torch.tensor([[0.5], [1.0], [1.5], [1.0]]))
    big = TensorDict({}, [100_000])
    one_hot = torch.zeros(100_000, dtype=torch.float16)
    one_hot[0] = 1.0
    with pytest.raises(NonFiniteWeightsError):  # self-normalised, 1e5 overflows float16: nothing is stored
        store_density_ratio(big, one_hot, key="w")
    assert "w" not in big.keys()
    with pytest.raises(ValueError, match="4 rows"):
        store_density_ratio(td, torch.ones(3))
    with pytest.raises(ValueError, match="ratio_network"):
        store_density_ratio(td)


def test_the_trainer_runs_stage_1_through_the_public_fitter(tmp_path):
    from tests.test_training import tiny_config
    from torchrl_wbrm.training import WBRMTrainer

    torch.set_num_threads(1)
    trainer = WBRMTrainer(tiny_config(ratio={"steps": 20, "eval_every": 10}, q={"steps": 2, "eval_every": 2}),
                          tmp_path, progress=False)
    assert isinstance(trainer.ratio_fitter, DensityRatioFitter)
    assert isinstance(trainer.ratio_fitter.loss_module, RobustDensityRatioLoss)
    assert trainer.ratio_fitter.loss_module.ratio_network is trainer.ratio_network
    trainer.run()
    assert trainer.ratio_fitter.num_steps == 20
    w = compute_density_ratio(trainer.ratio_network, trainer.q_train_data)
    torch.testing.assert_close(trainer.q_buffer[:]["density_ratio"], shape_weights(w, temper=trainer.cfg.ratio.temper))


# ---------------------------------------------------------------- inputs named, seeds, collapse, rows and weights
def test_too_small_sets_name_the_set():
    behaviour, expert = _samples(50, BEHAVIOUR_STD, 1), _samples(50, EXPERT_STD, 2)
    with pytest.raises(ValueError, match="The behaviour set has 1 sample"):
        fit_density_ratio(behaviour[:1], expert, steps=5)
    with pytest.raises(ValueError, match="The expert set has 0 sample"):
        fit_density_ratio(behaviour, expert[:0], steps=5)
    with pytest.raises(ValueError, match="The held-out expert set is empty"):
        DensityRatioFitter(DensityRatioNetwork(1, 1, num_cells=(8,)), behaviour, expert,
                           holdout=(behaviour[:5], expert[:0]))


@pytest.mark.parametrize("steps", [0, -5])
def test_steps_must_be_positive(steps):
    behaviour, expert = _samples(50, BEHAVIOUR_STD, 1), _samples(50, EXPERT_STD, 2)
    with pytest.raises(ValueError, match=f"steps must be a positive integer.*got {steps}"):
        fit_density_ratio(behaviour, expert, steps=steps)
    fitter = DensityRatioFitter(DensityRatioNetwork(1, 1, num_cells=(8,)), behaviour, expert, batch_size=16)
    with pytest.raises(ValueError, match="steps must be a positive integer"):
        fitter.fit(steps)


def test_the_same_seed_gives_the_same_fit_and_float64_data_fit_alike():
    """The network's initialisation and the batches come from ``seed``, not from the global generator (which is
    left as it was); float64 data are converted to the network's dtype and give the same fit."""
    behaviour, expert = _samples(400, BEHAVIOUR_STD, 1), _samples(200, EXPERT_STD, 2)

    def fit(b, e, seed):
        return fit_density_ratio(b, e, steps=30, eval_every=10, batch_size=64, num_cells=(16,), seed=seed)

    torch.manual_seed(0)
    first = fit(behaviour, expert, 3)
    state = torch.get_rng_state()
    torch.manual_seed(99)
    second = fit(behaviour, expert, 3)
    torch.manual_seed(0)
    fit(behaviour, expert, 3)
    assert torch.equal(torch.get_rng_state(), state)  # the caller's random state is untouched
    a, b = first.network.state_dict(), second.network.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a) and first.best_loss == second.best_loss
    other = fit(behaviour, expert, 4)
    assert other.best_loss != first.best_loss
    wide = fit(behaviour.apply(lambda x: x.double()), expert.apply(lambda x: x.double()), 3)
    assert wide.best_loss == pytest.approx(first.best_loss, abs=1e-5)


def test_a_fit_that_only_got_worse_returns_its_start_and_is_flagged():
    """Gradient ascent (Adam with maximize=True): every evaluation is worse than the start. The fitter keeps the
    initial state as its best (step 0), returns it, and flags ``ratio_collapse``; a real fit is not flagged."""
    behaviour, expert = _samples(400, BEHAVIOUR_STD, 1), _samples(200, EXPERT_STD, 2)
    torch.manual_seed(0)
    network = DensityRatioNetwork(1, 1, num_cells=(16,))
    start = {k: v.clone() for k, v in network.state_dict().items()}
    optimiser = torch.optim.Adam(network.parameters(), lr=0.05, maximize=True)
    fitter = DensityRatioFitter(network, behaviour, expert, batch_size=64, optimizer=optimiser)
    fit = fitter.fit(steps=60, eval_every=10)
    assert fit.history[-1]["held_out_loss"] > fitter.start_loss  # it did get worse
    assert fit.best_step == 0 and fit.best_loss == pytest.approx(fitter.start_loss)
    assert fit.ratio_collapse and fitter.ratio_collapse
    assert all(torch.equal(v, start[k]) for k, v in fit.network.state_dict().items())
    good = fit_density_ratio(behaviour, expert, steps=200, eval_every=20, batch_size=64, num_cells=(16,), lr=3e-3)
    assert not good.ratio_collapse and good.best_step > 0


def test_store_refuses_weights_that_are_not_one_per_row_and_empty_targets():
    rb = _buffer(_samples(10, BEHAVIOUR_STD, 7))
    with pytest.raises(ValueError, match=r"shape \(5, 2\) for 10 rows"):
        store_density_ratio(rb, torch.ones(5, 2))
    empty = TensorDictReplayBuffer(storage=LazyTensorStorage(10), batch_size=4)
    with pytest.raises(ValueError, match="The replay buffer is empty"):
        store_density_ratio(empty, torch.ones(0))
    with pytest.raises(ValueError, match="no rows to store weights under 'density_ratio'"):
        store_density_ratio(TensorDict({}, [0]), torch.ones(0))
    ints = store_density_ratio(_samples(4, BEHAVIOUR_STD, 6), torch.tensor([1, 2, 3, 2]))
    torch.testing.assert_close(ints, torch.tensor([0.5, 1.0, 1.5, 1.0]))


@pytest.mark.parametrize("storage", [LazyTensorStorage, LazyMemmapStorage])
def test_stored_weights_follow_their_rows(storage):
    """Rows written after store_density_ratio (here replacing rows 0-1 and filling rows 10-11 of a 12-row
    buffer) never carry another row's weight or 0: they hold none, a sample that draws them is refused by name,
    and storing again gives every row its own. Rows written with their own weight keep it."""
    from torchrl_wbrm.ratio import MissingWeightsError

    rb = TensorDictReplayBuffer(storage=storage(12), batch_size=12)
    first = _samples(10, BEHAVIOUR_STD, 8)
    if storage is LazyMemmapStorage:  # a locked storage takes no new entry: the data hold it from the first extend
        first["density_ratio"] = torch.zeros(10)
    rb.extend(first)
    store_density_ratio(rb, torch.arange(1.0, 11.0), self_normalise=False)
    rb.extend(_samples(4, BEHAVIOUR_STD, 9))  # rows 10, 11, 0, 1
    stored = rb.storage[:]["density_ratio"]
    assert torch.isnan(stored[[0, 1, 10, 11]]).all()
    torch.testing.assert_close(torch.as_tensor(stored[2:10]), torch.arange(3.0, 11.0))
    with pytest.raises(MissingWeightsError, match="hold no stored weight under 'density_ratio'.*store_density_ratio"):
        rb.sample()
    store_density_ratio(rb, torch.full((12,), 2.0), self_normalise=False)
    assert (rb.sample()["density_ratio"] == 2.0).all()
    own = _samples(2, BEHAVIOUR_STD, 10)
    own["density_ratio"] = torch.tensor([5.0, 7.0])
    rb.extend(own)  # rows 2, 3
    torch.testing.assert_close(torch.as_tensor(rb.storage[:]["density_ratio"][2:4]), torch.tensor([5.0, 7.0]))
    assert len(rb.transform) == 1  # storing again added no second transform


def test_a_locked_storage_without_the_entry_is_refused_in_one_line_and_keeps_its_rows():
    """A memory-mapped storage is locked: torchrl drops a new entry from its writes, so storing weights there is
    refused, naming the storage, the key and the fix, and nothing is written."""
    rb = TensorDictReplayBuffer(storage=LazyMemmapStorage(12), batch_size=4)
    rb.extend(_samples(10, BEHAVIOUR_STD, 8))
    before = rb.storage[:].clone()
    with pytest.raises(ValueError, match=r"^The replay buffer's LazyMemmapStorage is locked .* no 'density_ratio' "
                                         r"entry.*before the first extend") as err:
        store_density_ratio(rb, torch.ones(10))
    assert "\n" not in str(err.value)
    assert (rb.storage[:] == before).all() and "density_ratio" not in rb.storage[:].keys()
    assert len(rb.transform) == 0


def test_a_ratio_network_of_other_dimensions_is_refused_in_one_line():
    """A network fitted on 1-d observations and actions, given rows of 3-d observations, is named with the rows'
    shapes instead of torch's ``mat1 and mat2`` error; a network reading a key the data lack names it."""
    network = DensityRatioNetwork(1, 1, num_cells=(8,))
    rows = TensorDict({"observation": torch.randn(5, 3), "action": torch.randn(5, 1)}, [5])
    with pytest.raises(ValueError, match=r"per-row shapes \{'observation': \(3,\), 'action': \(1,\)\}") as info:
        store_density_ratio(rows, ratio_network=network)
    assert "\n" not in str(info.value)
    assert "density_ratio" not in rows.keys()
    with pytest.raises(KeyError, match="reads \\['action'\\]"):
        compute_density_ratio(network, TensorDict({"observation": torch.randn(5, 1)}, [5]))
