"""``baselines.bc.data``: what behaviour cloning clones. S^e (the default), S^e ∪ D, S^e ∪ D with D's rows weighted by
the stored ŵ (stage 1 runs for it, the loss is :func:`~torchrl_wbrm.objectives.functional.action_cloning`), or S^e
and D's true expert episodes, refused where the data do not say which those are."""
from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded

from tests.references import tiny_lqr_config
from torchrl_wbrm.algos import AlgoContext, build_algo, get_algo
from torchrl_wbrm.algos.bc import BC_DATA, cloned_data
from torchrl_wbrm.objectives.functional import action_cloning
from torchrl_wbrm.training.config import validate_config


def _d_and_e():
    """D: 6 rows of episodes 0, 1, 2 (weights 2, 0, 1), observation = row index; S^e: 2 rows, observation 10."""
    d = TensorDict({
        "observation": torch.arange(6.0).reshape(6, 1), "action": torch.linspace(-1, 1, 6).reshape(6, 1),
        "episode": torch.tensor([0, 0, 1, 1, 2, 2]),
        "density_ratio": torch.tensor([[2.0], [2.0], [0.0], [0.0], [1.0], [1.0]]),
        "next": {"reward": torch.zeros(6, 1)},
    }, [6])
    e = TensorDict({"observation": torch.full((2, 1), 10.0), "action": torch.full((2, 1), 0.5),
                    "episode": torch.tensor([7, 7])}, [2])
    return d, e


def test_union_clones_d_then_s_e_all_alike():
    d, e = _d_and_e()
    out = cloned_data("union", d, e)
    assert set(out.keys()) == {"observation", "action", "density_ratio"}
    assert out["observation"].flatten().tolist() == [0, 1, 2, 3, 4, 5, 10, 10]
    assert out["density_ratio"].flatten().tolist() == [1.0] * 8
    torch.testing.assert_close(out["action"][-2:], e["action"])
    assert d["density_ratio"][0].item() == 2.0  # D's stored weights are not changed


def test_weighted_keeps_d_stored_weights_and_gives_s_e_one():
    d, e = _d_and_e()
    out = cloned_data("weighted", d, e)
    assert out["density_ratio"].flatten().tolist() == [2, 2, 0, 0, 1, 1, 1, 1]
    assert out["density_ratio"].shape == (8, 1) and out["density_ratio"].dtype == d["density_ratio"].dtype


def test_oracle_keeps_s_e_and_only_ds_true_expert_episodes():
    d, e = _d_and_e()
    out = cloned_data("oracle", d, e, expert_episode_ids=[1, 9])  # 9: an expert episode that is not in D (S^b's)
    assert out["observation"].flatten().tolist() == [2, 3, 10, 10]
    assert out["density_ratio"].flatten().tolist() == [1.0] * 4
    assert cloned_data("oracle", d, e, expert_episode_ids=[])["observation"].flatten().tolist() == [10, 10]


def test_oracle_is_refused_in_one_line_where_the_data_do_not_say():
    d, e = _d_and_e()
    with pytest.raises(ValueError, match=r"^baselines\.bc\.data=oracle .* do not say which episodes") as err:
        cloned_data("oracle", d, e)
    assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match=r"baselines\.bc\.data=oracle needs D's episode ids"):
        cloned_data("oracle", d.exclude("episode"), e, expert_episode_ids=[1])
    with pytest.raises(ValueError, match=r"baselines\.bc\.data='expert'"):
        cloned_data("expert", d, e)


def test_the_setting_is_checked_and_stage_1_runs_only_for_the_ratios_settings():
    with pytest.raises(ValueError, match=r"^baselines\.bc\.data='everything' is not allowed: choose one of "
                                         r"\['expert', 'union', 'weighted', 'expert_like', 'oracle'\]\.$"):
        validate_config(tiny_lqr_config(algo="bc", baselines={"bc": {"data": "everything"}}))
    for data in BC_DATA:
        cfg = tiny_lqr_config(algo="bc", baselines={"bc": {"data": data}})
        validate_config(cfg)
        assert get_algo("bc").fits_ratio_for(cfg) is (data in ("weighted", "expert_like"))
        assert get_algo("wbrm").fits_ratio_for(cfg) and not get_algo("brm").fits_ratio_for(cfg)
    assert tiny_lqr_config(algo="bc").baselines.bc.data == "expert"  # the default is unchanged


def _context(data: str, true_expert=None):
    d, e = _d_and_e()
    torch.manual_seed(0)
    spec = Bounded(low=-torch.ones(1) * 2, high=torch.ones(1) * 2, shape=(1,))
    datasets = SimpleNamespace(metadata={"behaviour_expert_episode_ids": true_expert}, expert_samples=e)
    ctx = AlgoContext(cfg=tiny_lqr_config(algo="bc", baselines={"bc": {"data": data}}), observation_dim=1,
                      action_dim=1, action_spec=spec, gamma=0.9, q_initial_bias=0.0,
                      task=SimpleNamespace(datasets=datasets))
    return ctx, d, e


def test_the_weighted_step_descends_the_weighted_cloning_term():
    ctx, d, e = _context("weighted")
    algo = build_algo("bc", ctx)
    assert algo.uses_ratio and algo.data == "transitions"
    batch = algo.map_data(d)
    with algo.loss.actor_network_params.to_module(algo.policy):
        mu = algo.policy(batch.select("observation"))["action"].detach()
    expected = action_cloning(mu, batch["action"], torch.tensor([2.0]), batch["density_ratio"])
    figures = algo.step(batch, 0)
    torch.testing.assert_close(figures["loss_bc"], expected)
    # the rows of weight 0 (episode 1) do not enter the loss
    assert expected.item() != pytest.approx(action_cloning(mu, batch["action"], torch.tensor([2.0])).item())


@pytest.mark.parametrize("data", ["expert", "union", "oracle"])
def test_the_plain_settings_step_torchrls_bc_loss(data):
    ctx, d, e = _context(data, true_expert=[2])
    algo = build_algo("bc", ctx)
    assert not algo.uses_ratio and algo.data == ("expert" if data == "expert" else "transitions")
    batch = e if data == "expert" else algo.map_data(d)
    assert batch.shape[0] == {"expert": 2, "union": 8, "oracle": 4}[data]
    with algo.loss.actor_network_params.to_module(algo.policy):
        mu = algo.policy(batch.select("observation"))["action"].detach()
    figures = algo.step(batch, 0)
    torch.testing.assert_close(figures["loss_bc"], (mu - batch["action"]).pow(2).mean())


def test_oracle_is_refused_before_training_on_data_that_do_not_say():
    ctx, _, _ = _context("oracle", true_expert=None)
    with pytest.raises(ValueError, match=r"^baselines\.bc\.data=oracle clones D's true expert episodes"):
        build_algo("bc", ctx)
