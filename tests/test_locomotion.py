"""The MuJoCo locomotion experts (:mod:`torchrl_wbrm.policies.locomotion`) and their datasets
(:mod:`torchrl_wbrm.data.locomotion`).

Each committed policy is loaded safely and must reach the bar its record states over a few episodes; a crafted file
is refused with nothing run; the D4RL-style mixtures hold the expert share of the transitions they are named for.
"""
from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest
import torch

from torchrl_wbrm.data.locomotion import _interleave, mixture_plan
from torchrl_wbrm.policies.locomotion import (
    EXPERTS_DIR,
    LOCOMOTION_TASKS,
    LocomotionActor,
    evaluate_policy,
    load_locomotion_policy,
    locomotion_record,
)

needs_mujoco = pytest.mark.skipif(importlib.util.find_spec("mujoco") is None, reason="needs mujoco")

#: the committed policies: (task, level) for every ``<task>-<level>.pt`` beside its record
COMMITTED = sorted((p.stem.rsplit("-", 1)[0], p.stem.rsplit("-", 1)[1]) for p in EXPERTS_DIR.glob("*.pt"))


def test_every_committed_policy_has_its_record_and_every_record_its_weights():
    assert COMMITTED, "no locomotion policy is committed"
    records = sorted(p.stem for p in EXPERTS_DIR.glob("*.json"))
    assert records == sorted(f"{t}-{lvl}" for t, lvl in COMMITTED)
    for task, level in COMMITTED:
        assert task in LOCOMOTION_TASKS
        record = locomotion_record(task, level)
        for key in ("env_id", "seed", "frames", "return_mean", "return_ci95", "episodes", "test_bar"):
            assert key in record, (task, level, key)
        assert record["env_id"] == LOCOMOTION_TASKS[task]
        assert record["test_bar"] < record["return_mean"]


@needs_mujoco
@pytest.mark.parametrize("task,level", COMMITTED)
def test_a_committed_policy_reaches_the_bar_its_record_states(task, level):
    record = locomotion_record(task, level)
    actor = load_locomotion_policy(task, level)
    returns = evaluate_policy(actor, record["env_id"], episodes=3, seed=123)
    assert returns.mean() > record["test_bar"], (task, level, returns, record["test_bar"])


@needs_mujoco
def test_a_crafted_weights_file_is_refused_and_runs_nothing(tmp_path):
    import os

    marker = tmp_path / "ran"

    class Evil:
        def __reduce__(self):
            return (os.makedirs, (str(marker),))

    path = tmp_path / "evil.pt"
    torch.save({"net.0.weight": Evil()}, path)
    with pytest.raises(ValueError, match="evil.pt: not a policy's weights"):
        load_locomotion_policy("hopper", path=path)
    assert not marker.exists()
    # the right keys with the wrong shapes: refused by name too
    wrong = {k: torch.zeros(1) for k in LocomotionActor(11, 3).state_dict()}
    torch.save(wrong, path)
    with pytest.raises(ValueError, match="does not hold the Hopper-v5 actor's tensors"):
        load_locomotion_policy("hopper", path=path)


def test_an_unknown_task_is_refused_by_name():
    with pytest.raises(ValueError, match="'ant' is not one of"):
        load_locomotion_policy("ant")


def test_a_mixture_holds_its_share_of_the_transitions_not_of_the_episodes():
    rng = np.random.default_rng(0)
    expert = [1000] * 30
    random = list(rng.integers(10, 40, size=100_000))
    for pp in (1, 5, 10):
        k, m = mixture_plan(expert, random, 100_000, pp)
        total = sum(expert[:k]) + sum(random[:m])
        assert total >= 100_000 and total - 100_000 < 40
        share = sum(expert[:k]) / total
        assert sum(expert[:k]) >= pp / 100 * 100_000 and pp / 100 - 0.001 < share < pp / 100 + 0.011, (pp, share)
        assert k / (k + m) < share / 10  # a share of the episodes would be another data set
    with pytest.raises(ValueError, match="cannot give"):
        mixture_plan([1000] * 2, random, 100_000, 5)


def test_the_expert_episodes_are_spread_among_the_random_ones():
    order = _interleave(3, 9)
    assert [kind for kind, _ in order].count("expert") == 3
    positions = [i for i, (kind, _) in enumerate(order) if kind == "expert"]
    assert positions == [3, 6, 9]
    assert sorted(i for kind, i in order if kind == "random") == list(range(9))


@needs_mujoco
@pytest.mark.slow
def test_the_datasets_of_a_task_hold_their_make_up(tmp_path):
    from torchrl_wbrm.data.locomotion import make_locomotion_task

    task = COMMITTED[0][0]
    assert (task, "medium") in COMMITTED, f"{task} has no committed medium policy: its medium-v0 cannot be made"
    row = make_locomotion_task(task, tmp_path, transitions=3000, expert_shares=(5, 40), pool_episodes=2,
                               log=lambda line: None)
    made = {d["id"]: d for d in row["datasets"]}
    for pp in (5, 40):
        d = made[row[f"random_expert{pp:02d}"]]
        assert d["transitions"] >= 3000 and d["expert_transitions"] / d["transitions"] >= pp / 100
        meta = json.loads(next((tmp_path / row[f"random_expert{pp:02d}"]).rglob("metadata.json")).read_text())
        assert len(meta["expert_episode_ids"]) == d["expert_episodes"] >= 1
    # an existing id is refused before anything is collected
    with pytest.raises(FileExistsError):
        make_locomotion_task(task, tmp_path, transitions=3000, expert_shares=(5,), log=lambda line: None)
    with pytest.raises(ValueError, match="integer percentage"):
        make_locomotion_task(task, tmp_path / "other", transitions=3000, expert_shares=(0,))
