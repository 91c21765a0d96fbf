"""The selections on D's expert-like episodes (:func:`~torchrl_wbrm.ratio.expert_like_episodes`):
``q.select=expert_like_action`` delivers the evaluation whose actor clones them best, ``q.select=expert_like_return``
the one whose Q is closest to their discounted returns, each bootstrapped at its episode's end by the Bellman target
(:func:`~torchrl_wbrm.objectives.functional.bootstrapped_returns`). Where ŵ names no expert-like episode (ŵ ≡ 1)
both fall back to the held-out ŵ-weighted residual and say so."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from tests.references import tiny_lqr_config
from torchrl_wbrm.data.datasets import check_episodes_in_order
from torchrl_wbrm.objectives.functional import action_cloning, bootstrapped_returns
from torchrl_wbrm.ratio import compute_density_ratio, expert_like_episodes
from torchrl_wbrm.training import WBRMTrainer

pytestmark = pytest.mark.usefixtures("single_thread")  # tests/conftest.py: one torch thread per test


def _loop_returns(reward, target, episode, gamma):
    """G_t by the definition, row by row from the end."""
    g = [0.0] * len(reward)
    for t in reversed(range(len(reward))):
        last = t == len(reward) - 1 or episode[t + 1] != episode[t]
        g[t] = target[t] if last else reward[t] + gamma * g[t + 1]
    return torch.tensor(g, dtype=torch.float64)


# ---------------------------------------------------------------- the returns
def test_bootstrapped_returns_match_the_definition():
    gen = torch.Generator().manual_seed(0)
    lengths = [1, 7, 200, 3, 1]  # a one-row episode's return is its target alone
    episode = torch.cat([torch.full((n,), i) for i, n in zip([4, 0, 9, 2, 7], lengths)])
    reward = torch.randn(episode.numel(), generator=gen, dtype=torch.float64)
    target = torch.randn(episode.numel(), generator=gen, dtype=torch.float64) * 10
    got = bootstrapped_returns(reward, target, episode, 0.97)
    torch.testing.assert_close(got, _loop_returns(reward.tolist(), target.tolist(), episode.tolist(), 0.97))
    # only each episode's last target is read
    inner = torch.ones_like(episode, dtype=torch.bool)
    inner[torch.cumsum(torch.tensor(lengths), 0) - 1] = False
    torch.testing.assert_close(bootstrapped_returns(reward, torch.where(inner, 1e6, target), episode, 0.97), got)
    with pytest.raises(ValueError, match=r"one shape \[N\], got \(5,\), \(4,\) and \(5,\)"):
        bootstrapped_returns(torch.zeros(5), torch.zeros(4), torch.zeros(5, dtype=torch.long), 0.9)


def test_episodes_out_of_order_are_refused_naming_the_episode():
    obs = torch.arange(6.0).reshape(-1, 1)
    td = TensorDict({"observation": obs, "next": {"observation": obs + 1},
                     "episode": torch.tensor([3, 3, 5, 5, 3, 3])}, [6])
    with pytest.raises(ValueError, match=r"^D: episode 3's rows are not contiguous; each episode's rows must be "):
        check_episodes_in_order(td, "D")
    check_episodes_in_order(td[:4], "D")


# ---------------------------------------------------------------- in the trainer
def _run(tmp_path, name, select="expert_like_return", **overrides):
    cfg = tiny_lqr_config({"q": {"select": select, "eval_every": 20}}, **overrides)
    trainer = WBRMTrainer(cfg, tmp_path / name, progress=False)
    return trainer, trainer.run()


def test_wbrm_scores_q_against_the_expert_like_episodes_returns(tmp_path):
    """The figure is the mean (Q(x_t, a_t) − G_t)² over the rows of the episodes the raw ŵ calls expert-like, every
    evaluation records it, the run delivers the evaluation where it is lowest, and the results name it."""
    trainer, results = _run(tmp_path, "wbrm")
    d = trainer.q_train_data
    w = compute_density_ratio(trainer.ratio_network, d, chunk_size=8192)
    rows = expert_like_episodes(w, d["episode"])
    assert 0 < int(rows.sum()) < d.shape[0]  # this fit selects some episodes, not all
    assert torch.equal(trainer.selection.criterion.rows["observation"], d["observation"][rows])
    # the figure of the delivered parameters, by hand
    sel = d[rows].clone().set("density_ratio", torch.ones(int(rows.sum()), 1))
    with torch.no_grad():
        q, y = trainer.algo.bellman_loss.bellman_error(sel)
    g = _loop_returns(sel["next", "reward"].reshape(-1).tolist(), y.reshape(-1).tolist(),
                      sel["episode"].reshape(-1).tolist(), trainer.gamma)
    want = (q.reshape(-1).double() - g).pow(2).mean().item()
    assert results["final"]["expert_like_return_error"] == pytest.approx(want, rel=1e-4)
    _check_delivered(trainer, results, "expert_like_return_error")
    selection = results["selection"]
    assert (selection["select"], selection["figure"], selection["selected_step"]) == (
        "expert_like_return", "expert_like_return_error", results["final"]["selected_step"])
    assert selection["online_episodes_used_by_selection"] == 0


def _check_delivered(trainer, results, figure):
    """The last row is the delivered parameters' evaluation: the run's lowest ``figure``, and the same as its own
    evaluation's where it is an earlier one."""
    evaluations = [r for r in trainer.history if r["stage"] == "q"]
    assert all(figure in r for r in evaluations)
    earlier = {r["step"]: r[figure] for r in evaluations[:-1]}
    chosen = results["final"]["selected_step"]
    assert results["final"][figure] <= min(earlier.values())
    if chosen in earlier:
        assert results["final"][figure] == earlier[chosen]


def test_wbrm_scores_the_actor_against_the_expert_like_episodes_actions(tmp_path):
    """The figure is the actor's cloning error on the expert-like rows, in unit actions, as the cloning term's."""
    trainer, results = _run(tmp_path, "action", select="expert_like_action")
    d = trainer.selection.criterion.rows
    assert 0 < d.shape[0] < trainer.q_train_data.shape[0]
    spec = trainer.action_spec
    with torch.no_grad():
        mu = trainer.actor(d.select("observation").clone())["action"]
    want = action_cloning(mu, d["action"], (spec.space.high - spec.space.low) / 2).item()
    assert results["final"]["expert_like_action_error"] == pytest.approx(want, rel=1e-5)
    assert "expert_like_return_error" not in results["final"]
    _check_delivered(trainer, results, "expert_like_action_error")
    assert results["selection"]["figure"] == "expert_like_action_error"


@pytest.mark.parametrize("select", ["expert_like_action", "expert_like_return"])
def test_with_w_equal_to_one_it_falls_back_to_the_held_out_residual(tmp_path, select):
    """BRM (ŵ ≡ 1) has no expert-like episode: it selects by the held-out residual, as
    ``q.select=held_out_weighted_residual`` does, and says so."""
    trainer, results = _run(tmp_path, "brm", select=select, algo="brm")
    from torchrl_wbrm.training.selection import HeldOutWeightedResidual

    assert isinstance(trainer.selection.criterion, HeldOutWeightedResidual)
    assert results["selection"]["figure"] == "held_out_weighted_residual"
    assert all(not k.startswith("expert_like") for r in trainer.history if r["stage"] == "q" for k in r)
    _, plain = _run(tmp_path, "brm_residual", select="held_out_weighted_residual", algo="brm")
    assert results["final"]["selected_step"] == plain["final"]["selected_step"]
    assert results["final"]["regret"] == plain["final"]["regret"]
