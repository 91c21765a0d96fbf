"""``q.expert_bc_from_d``: the actor clones S^e together with D's expert-like episodes, those whose geometric mean
of the self-normalised stage-1 ŵ is above 1 (:func:`~torchrl_wbrm.ratio.expert_like_episodes`)."""
from __future__ import annotations

import pytest
import torch

from tests.references import tiny_lqr_config
from torchrl_wbrm.ratio import compute_density_ratio, expert_like_episodes
from torchrl_wbrm.training.config import WBRMConfig, validate_config


# ---------------------------------------------------------------- the rule
def test_known_answer_geometric_mean_of_the_self_normalised_ratio_above_one():
    # mean ŵ = 21 / 7 = 3; per episode, the geometric mean of ŵ / 3: ep 3: 4/3 = 1.33; ep 9: 3.2/3 = 1.07; ep 5:
    # 0.1/3; ep 0: (0.1·0.1·9.5)^(1/3)/3 = 0.15, though its arithmetic mean, 3.23, is above ŵ's (two of its steps
    # are far from the expert's)
    w = torch.tensor([4.0, 0.1, 4.0, 0.1, 9.5, 3.2, 0.1])
    episode = torch.tensor([3, 0, 3, 0, 0, 9, 5])  # rows of one episode need not be contiguous
    assert expert_like_episodes(w, episode).tolist() == [True, False, True, False, False, True, False]
    # [N, 1] weights and ids, as stored, and any positive scale of ŵ select the same rows
    assert expert_like_episodes(3 * w.reshape(-1, 1), episode.reshape(-1, 1)).tolist() == \
        expert_like_episodes(w, episode).tolist()


def test_a_flat_ratio_selects_nothing_and_a_zero_step_rules_an_episode_out():
    episode = torch.tensor([0, 0, 1, 1, 2])
    assert not expert_like_episodes(torch.full((5,), 0.7), episode).any()
    # mean ŵ 18.02: episode 0 is at 1.11; episode 1 has one step the expert never takes (ŵ = 0), its likelihood
    # ratio is 0 however high its other step
    assert expert_like_episodes(torch.tensor([20.0, 20.0, 0.0, 50.0, 0.1]), episode).tolist() == \
        [True, True, False, False, False]


def test_the_recorded_figures_count_the_true_episodes_a_threshold_could_separate():
    """``separable_true_episodes``: D's true expert episodes that score above every other episode of D. The data name
    episodes 3, 4, 7 and 11 the expert's; D holds the first three."""
    from torchrl_wbrm.ratio.weighting import expert_like_figures

    def figures(w, episode):
        rows, out = expert_like_figures(torch.tensor(w).reshape(-1, 1), torch.tensor(episode).reshape(-1, 1),
                                        [3, 4, 7, 11])
        return rows.tolist(), out

    # mean ŵ 11.7 / 7; the scores (geometric means of ŵ / mean ŵ): ep 3: 2.39, ep 4: 0.90, ep 7: 0.12, random ep 2:
    # 0.24, random ep 5: 0.06. Episodes 3 and 4 score above every random one; the even-odds test takes episode 3 only
    rows, out = figures([4.0, 4.0, 1.5, 1.5, 0.2, 0.4, 0.1], [3, 3, 4, 4, 7, 2, 5])
    assert rows == [True, True, False, False, False, False, False]
    assert out == {"expert_like_episodes": 1, "expert_like_rows": 2, "expert_like_true_episodes": 1,
                   "true_expert_episodes": 3, "separable_true_episodes": 2}
    # a random episode 6 scoring 2.15 (mean ŵ 2; ep 3 now 2.0): the test selects it with episode 3, and no threshold
    # separates any true episode from it
    rows, out = figures([4.0, 4.0, 1.5, 1.5, 0.2, 0.4, 0.1, 4.3], [3, 3, 4, 4, 7, 2, 5, 6])
    assert rows == [True, True, False, False, False, False, False, True]
    assert out == {"expert_like_episodes": 2, "expert_like_rows": 3, "expert_like_true_episodes": 1,
                   "true_expert_episodes": 3, "separable_true_episodes": 0}


def test_bad_input_is_refused_naming_the_shapes():
    with pytest.raises(ValueError, match="positive mean"):
        expert_like_episodes(torch.zeros(3), torch.tensor([0, 0, 1]))
    with pytest.raises(ValueError, match="one episode id per row"):
        expert_like_episodes(torch.ones(3), torch.tensor([0, 1]))
    with pytest.raises(ValueError, match="finite and non-negative"):
        expert_like_episodes(torch.tensor([1.0, -1.0, 3.0]), torch.tensor([0, 0, 1]))


# ---------------------------------------------------------------- the config
def test_the_setting_is_checked():
    assert WBRMConfig().q.expert_bc_from_d is False
    validate_config(tiny_lqr_config(q={"expert_bc_from_d": True}))
    validate_config(tiny_lqr_config(algo="brm", q={"expert_bc_from_d": True}))  # ŵ ≡ 1: the control
    with pytest.raises(ValueError, match="q.expert_bc_alpha > 0"):
        validate_config(tiny_lqr_config(q={"expert_bc_from_d": True, "expert_bc_alpha": 0.0}))
    with pytest.raises(ValueError, match="not algo=td3bc"):
        validate_config(tiny_lqr_config(algo="td3bc", q={"expert_bc_from_d": True}))


# ---------------------------------------------------------------- the trainer
def _after_stage_1(cfg, run_dir):
    from torchrl_wbrm.training import WBRMTrainer

    trainer = WBRMTrainer(cfg, run_dir, progress=False)
    trainer.run(until=0)
    return trainer


@pytest.mark.parametrize("algo", ["wbrm", "brm"])
def test_the_cloning_set_is_s_e_and_the_selected_episodes_of_d(tmp_path, algo):
    """After stage 1 the actor's cloning buffer holds S^e's rows, then the rows of D's episodes that the rule
    selects from the raw ŵ (before the residual's shaping); ŵ ≡ 1 (brm) adds none."""
    # a stage 1 that separates D's episodes: S^e is the expert, D a noisy behaviour
    trainer = _after_stage_1(tiny_lqr_config(algo=algo, q={"expert_bc_from_d": True}), tmp_path / algo)
    try:
        d = trainer.q_train_data
        cloning = trainer.algo.cloning
        expert = trainer.datasets.expert_samples[:]
        if algo == "brm":
            want = torch.zeros(d.shape[0], dtype=torch.bool)
        else:
            w = compute_density_ratio(trainer.ratio_network, d, chunk_size=8192)
            want = expert_like_episodes(w, d["episode"])
            assert 0 < int(want.sum()) < d.shape[0]  # this fit selects some episodes, not all
        stored = cloning.buffer.storage[: len(cloning.buffer)]
        assert cloning.added_rows == int(want.sum()) and len(cloning.buffer) == expert.shape[0] + cloning.added_rows
        for key in ("observation", "action"):
            torch.testing.assert_close(stored[key], torch.cat([expert[key], d[key][want]]))
        stats = trainer.weight_stats
        assert stats["expert_like_rows"] == cloning.added_rows
        assert stats["expert_like_episodes"] == d["episode"][want].unique().numel()
    finally:
        trainer.release()


@pytest.mark.parametrize("source", ["learned", "none"])
def test_bc_clones_s_e_and_the_episodes_the_raw_ratio_selects(tmp_path, source):
    """``algo=bc baselines.bc.data=expert_like``: the cloned rows are D's rows of the episodes the rule selects from
    the raw ŵ, then S^e's, every weight 1; ``ratio.source=none`` (ŵ ≡ 1) selects none, so S^e alone is cloned."""
    cfg = tiny_lqr_config(algo="bc", baselines={"bc": {"data": "expert_like"}}, ratio={"source": source})
    trainer = _after_stage_1(cfg, tmp_path / source)
    try:
        d, expert = trainer.q_train_data, trainer.datasets.expert_samples[:]
        if source == "none":
            assert trainer.ratio_network is None
            want = torch.zeros(d.shape[0], dtype=torch.bool)
        else:
            want = expert_like_episodes(compute_density_ratio(trainer.ratio_network, d, chunk_size=8192),
                                        d["episode"])
            assert 0 < int(want.sum()) < d.shape[0]  # this fit selects some episodes, not all
        cloned = trainer.q_buffer[:]
        for key in ("observation", "action"):
            torch.testing.assert_close(cloned[key], torch.cat([d[key][want], expert[key]]))
        assert (cloned["density_ratio"] == 1).all()
        assert trainer.weight_stats["expert_like_rows"] == int(want.sum())
    finally:
        trainer.release()


@pytest.mark.parametrize("layer, setting", [
    ({"q": {"expert_bc_from_d": True}}, r"q\.expert_bc_from_d=true"),
    ({"algo": "bc", "baselines": {"bc": {"data": "expert_like"}}}, r"algo=bc's cloning of D's expert-like episodes"),
    ({"ratio": {"aggregate": "episode"}}, r"ratio\.aggregate='episode'"),
    ({"q": {"select": "expert_like_return"}}, r"q\.select=expert_like_return"),
    ({"q": {"select": "expert_like_action"}}, r"q\.select=expert_like_action"),
])
def test_a_setting_that_reads_ds_episodes_is_refused_before_stage_1_on_data_without_ids(tmp_path, monkeypatch, layer,
                                                                                       setting):
    import torchrl_wbrm.training.trainer as trainer_module
    from torchrl_wbrm.training import WBRMTrainer

    load_run_data = trainer_module.load_run_data

    def without_ids(cfg, task):
        data = load_run_data(cfg, task)
        data.train = data.train.exclude("episode")
        return data

    monkeypatch.setattr(trainer_module, "load_run_data", without_ids)
    WBRMTrainer(tiny_lqr_config(), tmp_path / "defaults", progress=False).release()  # ŵ per transition: no ids read
    with pytest.raises(ValueError, match=rf"^{setting} needs D's episode ids \(key 'episode'\), which these data do "
                                         r"not hold: .+\.$"):
        WBRMTrainer(tiny_lqr_config(layer), tmp_path / "run", progress=False)


# ---------------------------------------------------------------- on a benchmark task
def test_stage_1_finds_the_expert_episodes_hidden_in_d(tmp_path):
    """Pendulum-v1's few-demonstration data, small: S^e 2 episodes of the expert pool, D the 10%-expert set's
    training episodes (2–3 of about 27 the expert's, by the benchmark's metadata). Every episode the test adds is one
    of D's true expert episodes, and it finds at least half of them (all of them on seeds 0, 1 and 2)."""
    from torchrl_wbrm.data.benchmark import few_demonstration_ids, make_benchmark_task

    make_benchmark_task("pendulum", tmp_path / "data", expert_episodes=2, behaviour_episodes=60,
                        reference_episodes=2, pool_episodes=10)
    ids = few_demonstration_ids("pendulum")
    cfg = WBRMConfig(env="minari", seed=0)
    m = cfg.env.minari
    m.data_path, m.expert, m.expert_episodes = str(tmp_path / "data"), ids["expert_pool"], 2
    m.behaviour = ids["behaviour_expert10"]
    cfg.q.expert_bc_from_d, cfg.ratio.steps, cfg.plots = True, 600, False
    trainer = _after_stage_1(cfg, tmp_path / "run")
    try:
        stats = trainer.weight_stats
    finally:
        trainer.release()
    assert stats["true_expert_episodes"] >= 2, stats  # D holds some of the 6 hidden expert episodes
    assert stats["expert_like_true_episodes"] == stats["expert_like_episodes"], stats  # nothing random added
    assert stats["expert_like_episodes"] >= stats["true_expert_episodes"] / 2, stats
    # with nothing random selected, every episode found scores above every other: a threshold could do no worse
    assert stats["expert_like_true_episodes"] <= stats["separable_true_episodes"] <= stats["true_expert_episodes"]
