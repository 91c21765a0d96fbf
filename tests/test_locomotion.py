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


def _tiny_run(out, **settings):
    """A Hopper SAC run of two 50-frame segments (25 random frames, then one update per frame) on tiny networks."""
    from torchrl_wbrm.policies.locomotion import _TrainConfig

    base = dict(task="hopper", seed=0, frames=100, out=out, init_random_frames=25, frames_per_batch=25,
                batch_size=16, save_every=50, eval_episodes=1, hidden=16)
    base.update(settings)
    return _TrainConfig(**base)


def _state(out):
    return torch.load(out / "state.pt", weights_only=True)


def _assert_same(a, b, where=""):
    if isinstance(a, dict):
        assert sorted(a, key=str) == sorted(b, key=str), where
        for key in a:
            _assert_same(a[key], b[key], f"{where}/{key}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_same(x, y, f"{where}/{i}")
    elif torch.is_tensor(a):
        assert a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b), where
    else:
        assert a == b, where


@needs_mujoco
def test_a_run_killed_mid_segment_resumes_bit_identical_to_one_never_stopped(tmp_path, monkeypatch):
    from torchrl_wbrm.policies import locomotion

    straight = _tiny_run(tmp_path / "straight")
    assert locomotion.train_locomotion_expert(straight, log=lambda line: None)["frames"] == 100

    # the second run dies at the end of its second segment's updates, before that segment's checkpoint
    evaluate = locomotion.evaluate_policy
    calls = []

    def dies_on_the_second_call(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return evaluate(*args, **kwargs)

    cut = _tiny_run(tmp_path / "cut")
    monkeypatch.setattr(locomotion, "evaluate_policy", dies_on_the_second_call)
    with pytest.raises(KeyboardInterrupt):
        locomotion.train_locomotion_expert(cut, log=lambda line: None)
    monkeypatch.setattr(locomotion, "evaluate_policy", evaluate)
    half = _state(cut.out)
    assert half["frames"] == 50 and not (cut.out / "hopper-00000100.pt").exists()
    rows = half["buffer"]["observation"]  # the state holds the filled rows, not the whole buffer's capacity
    assert len(rows) == 50 and rows.untyped_storage().nbytes() == rows.nbytes
    torch.manual_seed(12345)  # whatever the process did since: the state brings its own generators
    lines = []
    locomotion.train_locomotion_expert(cut, log=lines.append)
    assert json.loads(lines[0])["frames"] == 50  # it said where it resumed

    a, b = _state(straight.out), _state(cut.out)
    assert a["frames"] == b["frames"] == 100
    for key in ("loss", "optim", "torch_rng", "numpy_rng", "buffer", "settings"):
        _assert_same(a[key], b[key], key)
    assert a["loss"]["log_alpha"].item() != 0.0  # the updates ran: the temperature moved
    assert {k for k in a["loss"] if k.startswith("target_")}, "the target networks are part of the state"
    assert len(a["buffer"]["observation"]) == 100 and "loc" not in a["buffer"]
    assert [e["return_mean"] for e in a["log"]] == [e["return_mean"] for e in b["log"]]
    for frames in (50, 100):
        name = f"hopper-{frames:08d}.pt"
        _assert_same(torch.load(straight.out / name, weights_only=True), torch.load(cut.out / name, weights_only=True))
    # a finished run, called again, trains nothing more
    assert locomotion.train_locomotion_expert(cut, log=lambda line: None)["frames"] == 100


@needs_mujoco
def test_a_resume_with_other_settings_or_over_foreign_files_is_refused(tmp_path):
    import os

    from torchrl_wbrm.policies import locomotion

    cfg = _tiny_run(tmp_path / "run", frames=50)
    locomotion.train_locomotion_expert(cfg, log=lambda line: None)
    before = (cfg.out / "state.pt").read_bytes()
    with pytest.raises(ValueError, match=r"state.pt: the run was started with --frames 50, not 100;"):
        locomotion.train_locomotion_expert(_tiny_run(cfg.out, frames=100), log=lambda line: None)
    with pytest.raises(ValueError, match=r"started with --seed 0, not 1;"):
        locomotion.train_locomotion_expert(_tiny_run(cfg.out, seed=1), log=lambda line: None)
    assert (cfg.out / "state.pt").read_bytes() == before
    # checkpoints with no state are not overwritten
    (cfg.out / "state.pt").rename(tmp_path / "kept.pt")
    with pytest.raises(FileExistsError, match="holds hopper checkpoints but no state.pt"):
        locomotion.train_locomotion_expert(cfg, log=lambda line: None)
    # a crafted state runs nothing
    marker = tmp_path / "ran"

    class Evil:
        def __reduce__(self):
            return (os.makedirs, (str(marker),))

    torch.save({"format": 1, "settings": Evil()}, cfg.out / "state.pt")
    with pytest.raises(ValueError, match="state.pt: not a run state"):
        locomotion.train_locomotion_expert(cfg, log=lambda line: None)
    assert not marker.exists()


@needs_mujoco
@pytest.mark.parametrize("how", ["expert", "eval_env"])
def test_mujoco_warnings_leave_no_log_file_and_no_stdout_lines(tmp_path, how):
    """HalfCheetah-v5's model makes MuJoCo warn at every ``gymnasium.make``; MuJoCo's own handler would print it on
    stdout and append it to ``MUJOCO_LOG.TXT`` in the working directory. Loading an expert and making the evaluation
    env route it to one Python warning instead: nothing is written where the process stands."""
    import subprocess
    import sys

    code = {
        "expert": "from torchrl_wbrm.policies.locomotion import load_locomotion_policy as f\n"
                  "for _ in range(3): f('halfcheetah')\n",
        "eval_env": "from torchrl_wbrm.data.minari_data import make_minari_eval_env as f\n"
                    "f({'eval_env': 'HalfCheetah-v5'}, num_envs=3).close()\n",
    }[how]
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert list(tmp_path.iterdir()) == []  # no MUJOCO_LOG.TXT
    assert "WARNING" not in proc.stdout
    assert proc.stderr.count("MuJoCo: compiler attribute 'settotalmass'") == 1
