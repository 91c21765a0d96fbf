"""Bad data are refused before any training, in one line, with nothing written.

Tiny Minari datasets (a few Pendulum-v1-shaped episodes of made-up numbers, written locally with
``create_dataset_from_buffers``; nothing is downloaded) and a tiny saved dataset (``OfflineDatasets.save``), each with
one defect: a NaN or infinite value, an action outside the action space, spaces or envs that differ between the expert
and the behaviour data, an empty dataset, too few episodes, a missing id or missing dataset keys. Through the command
line, each refusal is one line naming the dataset (and, for a bad value, the episode, the step and the key), exits
non-zero without a traceback (one only with ``verbose=true``), and leaves the directory it ran in empty. The validators
are tested directly too, and so is the one read of the data a run makes (checked first, then handed to its trainer).
"""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from tests import forked, inprocess
from torchrl_wbrm.data import datasets as datasets_module
from torchrl_wbrm.data import minari_data
from torchrl_wbrm.data.datasets import OfflineDatasets, check_finite, read_saved_dataset
from torchrl_wbrm.data.minari_data import MinariDataConfig, check_minari_data, make_minari_datasets, write_minari_dataset

ROOT = Path(__file__).resolve().parents[1]
PENDULUM = "Pendulum-v1"
STEPS = 6  # per episode


def _episodes(count: int, *, seed: int, observation_dim: int = 3, actions=None) -> list[dict]:
    """``count`` episodes of ``STEPS`` steps of finite, in-bounds made-up numbers (Pendulum-v1's shapes and box)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        out.append({
            "observations": rng.uniform(-1.0, 1.0, (STEPS + 1, observation_dim)).astype(np.float32),
            "actions": (rng.uniform(-2.0, 2.0, (STEPS, 1)).astype(np.float32) if actions is None
                        else rng.integers(0, actions, STEPS)),
            "rewards": rng.uniform(-1.0, 0.0, STEPS),
            "terminations": np.zeros(STEPS, bool),
            "truncations": np.r_[np.zeros(STEPS - 1, bool), [True]],
        })
    return out


def _with(episodes: list[dict], key: str, episode: int, step: int, value) -> list[dict]:
    episodes[episode][key][step] = value
    return episodes


def _box(dim: int, bound: float):
    from gymnasium import spaces

    return spaces.Box(-bound, bound, (dim,), np.float32)


@pytest.fixture(scope="module")
def bad_data(tmp_path_factory) -> dict:
    """The Minari data path and the saved dataset's folder, with the datasets written once for this file."""
    from gymnasium import spaces

    from torchrl_wbrm.data.minari_examples import register_reshaped_env

    root = tmp_path_factory.mktemp("minari_bad")
    same_spaces = register_reshaped_env(PENDULUM, action_shape=(1,))  # Pendulum-v1's spaces, another env id
    written = {
        "good/expert-v0": (_episodes(4, seed=0), {"env": PENDULUM}),
        "good/behaviour-v0": (_episodes(6, seed=1), {"env": PENDULUM}),
        "nan/behaviour-v0": (_with(_episodes(6, seed=2), "rewards", 3, 2, np.nan), {"env": PENDULUM}),
        "inf/expert-v0": (_with(_episodes(4, seed=3), "observations", 1, 4, np.inf), {"env": PENDULUM}),
        "nanaction/behaviour-v0": (_with(_episodes(6, seed=4), "actions", 2, 0, np.nan), {"env": PENDULUM}),
        "outside/behaviour-v0": (_with(_episodes(6, seed=5), "actions", 2, 1, 2.5), {"env": PENDULUM}),
        "otherspaces/behaviour-v0": (_episodes(6, seed=6, observation_dim=2),
                                     {"observation_space": _box(2, 1.0), "action_space": _box(1, 2.0)}),
        "otherenv/behaviour-v0": (_episodes(6, seed=7), {"env": same_spaces}),
        "empty/behaviour-v0": ([], {"observation_space": _box(3, 8.0), "action_space": _box(1, 2.0)}),
        "few/behaviour-v0": (_episodes(3, seed=8), {"env": PENDULUM}),
        "discrete/expert-v0": (_episodes(4, seed=9, actions=2),
                               {"observation_space": _box(3, 1.0), "action_space": spaces.Discrete(2)}),
        "discrete/behaviour-v0": (_with(_episodes(6, seed=10, actions=2), "actions", 4, 3, 2),
                                  {"observation_space": _box(3, 1.0), "action_space": spaces.Discrete(2)}),
    }
    for dataset_id, (episodes, env) in written.items():
        write_minari_dataset(dataset_id, episodes, data_path=root, **env)
    for dataset_id, entry_point in FORGED.items():  # a recorded env spec whose entry point would write a file
        write_minari_dataset(dataset_id, _episodes(4, seed=11), data_path=root, env=PENDULUM)
        metadata = root / dataset_id / "data" / "metadata.json"
        meta = json.loads(metadata.read_text())
        spec = json.loads(meta["env_spec"])
        spec.update(entry_point=entry_point, kwargs={"file": "MARKER", "mode": "w"})
        meta["env_spec"] = json.dumps(spec)
        metadata.write_text(json.dumps(meta))
    assert same_spaces == "torchrl_wbrm/Pendulum_a1-v1"
    return {"data_path": str(root), "saved": _saved_dataset_with_nan(tmp_path_factory.mktemp("saved_bad"))}


#: datasets whose recorded env spec names another entry point than gymnasium's for Pendulum-v1; gymnasium.make of
#: the spec would call ``builtins.open("MARKER", "w")`` in the directory the command runs in
FORGED = {"forged/expert-v0": "builtins:open"}


def _saved_dataset_with_nan(path: Path) -> dict:
    """A saved dataset (8 behaviour episodes, 4 expert ones) whose transitions set holds one NaN reward, at step 2 of
    its first episode, with ``metadata.json``'s checksum updated: the files verify, the number does not."""
    rng = torch.Generator().manual_seed(0)
    episodes, steps = 12, STEPS
    n = episodes * steps
    obs = torch.randn(n, 2, generator=rng)
    last = (torch.arange(n) % steps == steps - 1).unsqueeze(-1)
    data = TensorDict({
        "observation": obs, "action": torch.rand(n, 1, generator=rng),
        "episode": torch.arange(n) // steps,
        "next": {"observation": torch.randn(n, 2, generator=rng), "reward": torch.rand(n, 1, generator=rng),
                 "done": last, "terminated": torch.zeros(n, 1, dtype=torch.bool), "truncated": last},
    }, batch_size=[n])
    behaviour, expert = data[: 8 * steps], data[8 * steps:]
    OfflineDatasets.from_behaviour_and_expert(
        behaviour, expert.select("observation", "action", "episode"), generator=torch.Generator().manual_seed(1),
    ).save(path)
    meta = json.loads((path / "metadata.json").read_text())
    entry = meta["files"]["transitions"]["next/reward"]
    episode_ids = torch.from_numpy(np.fromfile(path / meta["files"]["transitions"]["episode"]["file"], np.int64))
    episode = int(episode_ids[0])
    row = int((episode_ids == episode).nonzero()[2])
    file = path / entry["file"]
    values = np.fromfile(file, np.float32)
    values[row] = np.nan
    values.tofile(file)
    entry["sha256"] = hashlib.sha256(file.read_bytes()).hexdigest()
    (path / "metadata.json").write_text(json.dumps(meta))
    return {"path": str(path), "episode": episode, "row": row}


def _minari(bad_data, expert: str, behaviour: str) -> list[str]:
    return ["env=minari", f"env.minari.expert={expert}", f"env.minari.behaviour={behaviour}",
            f"env.minari.data_path={bad_data['data_path']}"]


#: name -> (the command's overrides, given the fixture; what its one line must say)
CLI_CASES = {
    "nan_reward": (lambda d: _minari(d, "good/expert-v0", "nan/behaviour-v0"),
                   ["Minari behaviour dataset 'nan/behaviour-v0': episode 3, step 2: rewards hold nan"]),
    "infinite_observation": (lambda d: _minari(d, "inf/expert-v0", "good/behaviour-v0"),
                             ["Minari expert dataset 'inf/expert-v0': episode 1, step 4: observations hold",
                              "inf", "must be finite"]),
    "action_outside_its_space": (lambda d: _minari(d, "good/expert-v0", "outside/behaviour-v0"),
                                 ["Minari behaviour dataset 'outside/behaviour-v0': episode 2, step 1: the action "
                                  "[2.5] lies outside the dataset's action space Box(-2.0, 2.0, (1,), float32)"]),
    "no_dataset_keys": (lambda d: ["env=minari"],
                        ["No Minari dataset given in env.minari.expert and env.minari.behaviour",
                         "set env.minari.expert=<id or path> and env.minari.behaviour=<id or path>"]),
    "dataset_id_not_found": (lambda d: _minari(d, "nowhere/expert-v0", "good/behaviour-v0"),
                             ["Minari dataset 'nowhere/expert-v0' not found", "Nothing is downloaded"]),
    "different_spaces": (lambda d: _minari(d, "good/expert-v0", "otherspaces/behaviour-v0"),
                         ["different observation spaces", "expert 'good/expert-v0'",
                          "behaviour 'otherspaces/behaviour-v0'"]),
    "different_envs": (lambda d: _minari(d, "good/expert-v0", "otherenv/behaviour-v0"),
                       ["different envs", "from 'Pendulum-v1'", "from 'torchrl_wbrm/Pendulum_a1-v1'"]),
    "empty_dataset": (lambda d: _minari(d, "good/expert-v0", "empty/behaviour-v0"),
                      ["Minari behaviour dataset 'empty/behaviour-v0' holds no steps (0 episodes)"]),
    "recorded_entry_point_not_gymnasiums": (
        lambda d: _minari(d, "forged/expert-v0", "good/behaviour-v0"),
        ["Minari dataset 'forged/expert-v0' records the env 'Pendulum-v1' with the entry point 'builtins:open'",
         "not the registered 'gymnasium.envs.classic_control.pendulum:PendulumEnv'", "is not run"]),
    "nan_in_a_saved_dataset": (lambda d: ["env=lqr_exp1", f"env.lqr_data.dataset_dir={d['saved']['path']}"],
                               ["its transitions set: episode", "step 2 (row", "'next/reward' is nan"]),
}


def _recipe(cwd: Path, overrides: list[str], data_path: str, *, process: bool = False) -> subprocess.CompletedProcess:
    """``python recipes/wbrm_offline.py <overrides>`` in ``cwd``: in this process (:mod:`tests.inprocess`), or, with
    ``process``, in a process of its own (:mod:`tests.forked`)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg", "MINARI_DATASETS_PATH": data_path}
    if not process:
        return inprocess.recipe(*overrides, cwd=cwd, env=env)
    return forked.run_forked(ROOT / "recipes" / "wbrm_offline.py", *overrides, cwd=cwd, env=env)


@pytest.mark.parametrize("case", list(CLI_CASES))
def test_the_command_refuses_bad_data_in_one_line_and_writes_nothing(case, bad_data, tmp_path):
    overrides, expected = CLI_CASES[case]
    # one case in a process of its own; the others in this process (the same code, without a process's imports)
    proc = _recipe(tmp_path, overrides(bad_data), bad_data["data_path"], process=case == "nan_reward")
    output = proc.stdout + proc.stderr
    assert proc.returncode != 0, output
    assert "Traceback" not in output, output
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("Refused (nothing was written): "), output
    for fragment in (expected if case != "nan_in_a_saved_dataset" else
                     [*expected, f"Dataset at {bad_data['saved']['path']}",
                      f"episode {bad_data['saved']['episode']}, step 2 (row {bad_data['saved']['row']})"]):
        assert fragment in last, (fragment, last)
    assert list(tmp_path.iterdir()) == [], "a refused command wrote into the directory it ran in"


def test_verbose_shows_the_traceback_and_still_writes_nothing(bad_data, tmp_path):
    proc = _recipe(tmp_path, [*_minari(bad_data, "good/expert-v0", "nan/behaviour-v0"), "verbose=true"],
                   bad_data["data_path"])
    assert proc.returncode != 0
    assert "Traceback" in proc.stderr and "_check_episode" in proc.stderr
    assert proc.stderr.strip().splitlines()[-1].startswith("Refused (nothing was written): Minari behaviour dataset")
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------------------------- the validators


def _config(bad_data, expert: str, behaviour: str, **kw) -> MinariDataConfig:
    return MinariDataConfig(expert=expert, behaviour=behaviour, data_path=bad_data["data_path"], **kw)


@pytest.mark.parametrize("expert, behaviour, error, fragments", [
    ("good/expert-v0", "nan/behaviour-v0", ValueError, ["'nan/behaviour-v0': episode 3, step 2: rewards hold nan"]),
    ("inf/expert-v0", "good/behaviour-v0", ValueError, ["'inf/expert-v0': episode 1, step 4: observations hold"]),
    ("good/expert-v0", "nanaction/behaviour-v0", ValueError,
     ["'nanaction/behaviour-v0': episode 2, step 0: actions hold [nan]"]),
    ("good/expert-v0", "outside/behaviour-v0", ValueError, ["episode 2, step 1: the action [2.5] lies outside"]),
    ("discrete/expert-v0", "discrete/behaviour-v0", ValueError,
     ["'discrete/behaviour-v0': episode 4, step 3: the action 2 lies outside the dataset's action space Discrete(2)"]),
    ("good/expert-v0", "otherspaces/behaviour-v0", ValueError, ["different observation spaces"]),
    ("good/expert-v0", "otherenv/behaviour-v0", ValueError, ["come from different envs"]),
    ("good/expert-v0", "empty/behaviour-v0", ValueError, ["'empty/behaviour-v0' holds no steps (0 episodes)"]),
    ("good/expert-v0", "few/behaviour-v0", ValueError, ["'few/behaviour-v0' holds 3 episode(s)", "at least 4"]),
    ("nowhere/expert-v0", "good/behaviour-v0", FileNotFoundError, ["'nowhere/expert-v0' not found"]),
    ("", "good/behaviour-v0", ValueError, ["No Minari dataset given in env.minari.expert"]),
])
def test_check_minari_data_refuses_naming_what_is_wrong(bad_data, expert, behaviour, error, fragments):
    cfg = _config(bad_data, expert, behaviour)
    for refuse in (check_minari_data, make_minari_datasets):  # the reader refuses alike: bad data never train
        with pytest.raises(error) as err:
            refuse(cfg)
        message = str(err.value)
        assert "\n" not in message
        for fragment in fragments:
            assert fragment in message, (fragment, message)


def test_good_minari_data_pass_and_are_read_once_per_run(bad_data, monkeypatch):
    """A run's check holds its read for the trainer's make_minari_datasets (once); a changed file is read again."""
    calls = []
    original = minari_data.read_minari_transitions
    monkeypatch.setattr(minari_data, "read_minari_transitions", lambda *a, **k: calls.append(1) or original(*a, **k))
    cfg = _config(bad_data, "good/expert-v0", "good/behaviour-v0")
    cfg.cache = False  # every read of the episodes counted (the transitions cache has its own tests)
    check_minari_data(cfg, keep=True)
    assert len(calls) == 2
    datasets = make_minari_datasets(cfg)
    assert len(calls) == 2  # the check's read, not a second one
    assert datasets.sizes()["expert_samples"] == 4 * STEPS
    make_minari_datasets(cfg)
    assert len(calls) == 4  # held once only
    check_minari_data(cfg, keep=True)
    behaviour = minari_data.resolve_minari_dataset("good/behaviour-v0", bad_data["data_path"])
    stat = (behaviour / "metadata.json").stat()
    os.utime(behaviour / "metadata.json", ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))
    make_minari_datasets(cfg)
    assert len(calls) == 8  # the files changed since the check: read (and checked) again


def test_a_saved_dataset_with_a_nan_is_refused_naming_where(bad_data):
    saved = bad_data["saved"]
    where = f"Dataset at {saved['path']}, its transitions set: episode {saved['episode']}, step 2 (row {saved['row']})"
    for read in (read_saved_dataset, OfflineDatasets.load):
        with pytest.raises(ValueError) as err:
            read(saved["path"])
        assert str(err.value).startswith(f"{where}: 'next/reward' is nan;"), str(err.value)


def test_a_saved_dataset_is_read_once_per_run(tmp_path, monkeypatch):
    """read_saved_dataset(keep=True) (a run's check) hands its read to the trainer's OfflineDatasets.load, once."""
    n = 8 * STEPS
    data = TensorDict({
        "observation": torch.zeros(n, 2), "action": torch.zeros(n, 1), "episode": torch.arange(n) // STEPS,
        "next": {"observation": torch.zeros(n, 2), "reward": torch.ones(n, 1), "done": torch.zeros(n, 1, dtype=torch.bool),
                 "terminated": torch.zeros(n, 1, dtype=torch.bool), "truncated": torch.zeros(n, 1, dtype=torch.bool)},
    }, batch_size=[n])
    OfflineDatasets.from_behaviour_and_expert(data, data[:STEPS].select("observation", "action", "episode")).save(tmp_path)
    calls = []
    original = datasets_module._read_verified_part
    monkeypatch.setattr(datasets_module, "_read_verified_part", lambda *a: calls.append(1) or original(*a))
    read_saved_dataset(tmp_path, keep=True)
    assert len(calls) == 3
    assert OfflineDatasets.load(tmp_path).sizes()["expert_samples"] == STEPS
    assert len(calls) == 3
    OfflineDatasets.load(tmp_path)
    assert len(calls) == 6


def test_check_finite_names_the_episode_step_and_key():
    td = TensorDict({"observation": torch.zeros(6, 2), "episode": torch.tensor([5, 5, 7, 5, 7, 7]),
                     "next": {"reward": torch.zeros(6, 1)}}, batch_size=[6])
    check_finite(td, "The set")
    td["next", "reward"][4, 0] = float("-inf")
    td["observation"][5, 1] = float("nan")
    with pytest.raises(ValueError, match=r"^The set: episode 7, step 1 \(row 4\): 'next/reward' is -inf;"):
        check_finite(td, "The set")
    with pytest.raises(ValueError, match=r"^The set: row 4: 'next/reward' is -inf;"):
        check_finite(td.exclude("episode"), "The set")


def test_a_recorded_entry_point_is_not_run(bad_data, tmp_path, monkeypatch):
    """The forged dataset's spec would run its entry point under ``gymnasium.make`` (shown first, in a folder of its
    own); the data check refuses it unrun, and ``env.minari.eval_env`` (a registered id) makes the run possible."""
    import gymnasium as gym
    from gymnasium.envs.registration import EnvSpec

    meta = json.loads((Path(bad_data["data_path"]) / "forged/expert-v0/data/metadata.json").read_text())
    monkeypatch.chdir(tmp_path)
    with pytest.raises(Exception):
        gym.make(EnvSpec.from_json(meta["env_spec"]))
    assert (tmp_path / "MARKER").exists()  # the payload is real
    (tmp_path / "MARKER").unlink()
    with pytest.raises(ValueError, match="'builtins:open'.*is not run"):
        check_minari_data(_config(bad_data, "forged/expert-v0", "good/behaviour-v0"))
    assert list(tmp_path.iterdir()) == []
    check_minari_data(_config(bad_data, "forged/expert-v0", "good/behaviour-v0", eval_env=PENDULUM))
