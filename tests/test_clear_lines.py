"""One clear line for every failure, before anything is written where it can be checked first; logs hold each step
once.

Built as the probes did it: Minari datasets with 1e30 rewards, an overflowing episode sum, an unbounded action box,
a recorded time limit shorter than the episodes, action bounds 10x the env's, observations 100x outside their space,
truncated files; a checkpoint whose config is a string; a multi-seed run killed (SIGKILL) after its first seed, then
resumed with the command it printed; Ctrl-C in a multi-seed run in a directory whose name holds a space; a write that
fails (a full disk); a resumed run's CSV logs; wandb's folders; the Python API's logs.
"""
from __future__ import annotations

import json
import os
import shlex
import shutil
import signal
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from tests import forked, inprocess
from tests.references import tiny_lqr_config
from tests.test_data_validation import PENDULUM, _box, _episodes, _with
from torchrl_wbrm.data.minari_data import MinariDataConfig, check_minari_data, write_minari_dataset
from torchrl_wbrm.training import WBRMTrainer

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.usefixtures("single_thread")  # tests/conftest.py: one torch thread per test

#: the tiny LQR config (tests/references.py) as recipe overrides
TINY = [
    "env.lqr_data.behaviour_episodes=40", "env.lqr_data.expert_episodes=20", "env.lqr_data.parallel_envs=20",
    "ratio.steps=30", "ratio.batch_size=64", "ratio.eval_every=10", "ratio.num_cells=[16,16]",
    "q.steps=40", "q.batch_size=32", "q.eval_every=20", "q.num_cells=[16,16]", "q.actor_num_cells=[16,16]",
    "eval.offline_value=false", "eval.episodes=50", "eval.train_episodes=20", "eval.q_samples=300", "logger.backend=", "logger.log_every=5",
    "plots=false",
]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}


def tiny(**overrides):
    return tiny_lqr_config({"checkpoint_every": 10}, **overrides)


def one_line(text: str) -> str:
    lines = [line for line in text.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in text, text[-3000:]
    return lines[0]


# ---------------------------------------------------------------------- Minari data that do not match their env
@pytest.fixture(scope="module")
def minari_data(tmp_path_factory) -> Path:
    from gymnasium.envs.registration import EnvSpec

    root = tmp_path_factory.mktemp("minari_clear")
    long_episodes = [{**ep, "observations": np.tile(ep["observations"][:1], (41, 1)),
                      "actions": np.zeros((40, 1), np.float32), "rewards": np.zeros(40),
                      "terminations": np.zeros(40, bool), "truncations": np.r_[np.zeros(39, bool), [True]]}
                     for ep in _episodes(6, seed=3)]
    written = {
        "good/expert-v0": (_episodes(4, seed=0), {"env": PENDULUM}),
        "good/behaviour-v0": (_episodes(6, seed=1), {"env": PENDULUM}),
        "huge/behaviour-v0": (_with(_episodes(6, seed=2), "rewards", 3, 2, 1e30), {"env": PENDULUM}),
        "sum/behaviour-v0": (_with(_with(_episodes(6, seed=2), "rewards", 4, 1, -1.5e19), "rewards", 4, 3, -1.5e19),
                             {"env": PENDULUM}),
        "unbounded/expert-v0": (_episodes(4, seed=0), {"observation_space": _box(3, 8.0),
                                                       "action_space": _box(1, np.inf)}),
        "unbounded/behaviour-v0": (_episodes(6, seed=1), {"observation_space": _box(3, 8.0),
                                                          "action_space": _box(1, np.inf)}),
        "wide/expert-v0": (_episodes(4, seed=0), {"env": PENDULUM}),
        "wide/behaviour-v0": (_episodes(6, seed=1), {"env": PENDULUM}),
        "far/behaviour-v0": (_with(_episodes(6, seed=4), "observations", 2, 3, np.float32([100.0, 0.0, 0.0])),
                             {"env": PENDULUM}),
        "short/expert-v0": (long_episodes[:4], {"env": PENDULUM}),
        "short/behaviour-v0": (long_episodes, {"env": PENDULUM}),
    }
    for dataset_id, (episodes, env) in written.items():
        write_minari_dataset(dataset_id, episodes, data_path=root, **env)
    for dataset_id in ("wide/expert-v0", "wide/behaviour-v0"):  # actions declared Box(-20, 20), Pendulum's (-2, 2)
        meta_file = root / dataset_id / "data" / "metadata.json"
        meta = json.loads(meta_file.read_text())
        space = json.loads(meta["action_space"])
        space.update(low=[-20.0], high=[20.0])
        meta["action_space"] = json.dumps(space)
        meta_file.write_text(json.dumps(meta))
    for dataset_id in ("short/expert-v0", "short/behaviour-v0"):  # a recorded time limit of 20 for 40-step episodes
        meta_file = root / dataset_id / "data" / "metadata.json"
        meta = json.loads(meta_file.read_text())
        spec = EnvSpec.from_json(meta["env_spec"])
        spec.max_episode_steps = 20
        meta["env_spec"] = spec.to_json()
        meta_file.write_text(json.dumps(meta))
    return root


def _check(root: Path, expert: str, behaviour: str, **kw) -> str:
    with pytest.raises(ValueError) as err:
        check_minari_data(MinariDataConfig(expert=expert, behaviour=behaviour, data_path=str(root), **kw))
    assert "\n" not in str(err.value)
    return str(err.value)


def test_rewards_of_1e30_are_refused_naming_the_dataset_episode_and_step(minari_data):
    message = _check(minari_data, "good/expert-v0", "huge/behaviour-v0")
    assert message.startswith("Minari behaviour dataset 'huge/behaviour-v0': episode 3, step 2: rewards hold 1e+30")
    assert "square overflows float32" in message


def test_an_episode_whose_reward_sum_overflows_is_refused(minari_data):
    message = _check(minari_data, "good/expert-v0", "sum/behaviour-v0")
    assert message.startswith("Minari behaviour dataset 'sum/behaviour-v0': episode 4: its rewards sum to 3e+19")


def test_a_saved_dataset_with_a_1e30_reward_is_refused(tmp_path):
    from torchrl_wbrm.data.datasets import OfflineDatasets, read_saved_dataset
    from torchrl_wbrm.tasks import get_task

    datasets = get_task(tiny().env).make_datasets(seed=0)
    d = datasets.transitions[:].clone()
    OfflineDatasets.from_tensordicts(d, datasets.behaviour_samples[:], datasets.expert_samples[:]).save(tmp_path / "ds")
    d["next", "reward"][7] = 1e30
    with pytest.raises(ValueError) as err:  # refused when the sets are built, before anything is saved
        OfflineDatasets.from_tensordicts(d, datasets.behaviour_samples[:], datasets.expert_samples[:])
    assert "(row 7): 'next/reward' is 1e+30, beyond 1.84e+19 in magnitude" in str(err.value)
    # and in a saved dataset whose file was changed (its checksum updated): refused when read
    meta = json.loads((tmp_path / "ds" / "metadata.json").read_text())
    entry = meta["files"]["transitions"]["next/reward"]
    values = np.fromfile(tmp_path / "ds" / entry["file"], np.float32)
    values[7] = 1e30
    values.tofile(tmp_path / "ds" / entry["file"])
    import hashlib

    entry["sha256"] = hashlib.sha256((tmp_path / "ds" / entry["file"]).read_bytes()).hexdigest()
    (tmp_path / "ds" / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError) as err:
        read_saved_dataset(tmp_path / "ds")
    assert "(row 7): 'next/reward' is 1e+30, beyond 1.84e+19 in magnitude" in str(err.value)


def test_an_unbounded_action_box_is_refused_in_one_line(minari_data):
    message = _check(minari_data, "unbounded/expert-v0", "unbounded/behaviour-v0")
    assert "the action space Box(-inf, inf, (1,), float32) is unbounded" in message


def test_action_bounds_other_than_the_envs_are_refused(minari_data):
    message = _check(minari_data, "wide/expert-v0", "wide/behaviour-v0")
    assert "its action bounds Box(-2.0, 2.0, (1,), float32) differ from the Minari datasets' Box(-20.0, 20.0" in message


def test_a_time_limit_shorter_than_the_data_episodes_is_refused(minari_data):
    message = _check(minari_data, "short/expert-v0", "short/behaviour-v0")
    assert "it ends episodes after 20 steps (max_episode_steps), but the Minari datasets hold episodes of 40 steps" \
        in message
    # the registered env (200 steps) is fine
    check_minari_data(MinariDataConfig(expert="short/expert-v0", behaviour="short/behaviour-v0",
                                       data_path=str(minari_data), eval_env=PENDULUM))


def test_observations_far_outside_their_space_are_refused(minari_data):
    message = _check(minari_data, "good/expert-v0", "far/behaviour-v0")
    assert message.startswith("Minari behaviour dataset 'far/behaviour-v0': episode 2, step 3: the observation "
                              "[100.0, 0.0, 0.0] lies far outside the dataset's observation space")


@pytest.mark.parametrize("eval_env, named", [
    ("MountainCarContinuous-v0", "its observations have the shape (2,), the Minari datasets' (3,)"),
    ("NoSuchEnv-v0", "the env cannot be made (NameNotFound"),
])
def test_an_eval_env_of_another_shape_or_an_unknown_id_is_refused(minari_data, eval_env, named):
    message = _check(minari_data, "good/expert-v0", "good/behaviour-v0", eval_env=eval_env)
    assert message.startswith(f"env.minari.eval_env={eval_env}: ") and named in message


@pytest.mark.parametrize("damage", ["metadata", "hdf5"])
def test_a_truncated_minari_dataset_is_named_in_one_line(minari_data, tmp_path, damage):
    root = tmp_path / "data"
    shutil.copytree(minari_data / "good", root / "good")
    target = root / "good" / "behaviour-v0" / "data" / ("metadata.json" if damage == "metadata" else "main_data.hdf5")
    os.truncate(target, target.stat().st_size // 2)
    message = _check(root, "good/expert-v0", "good/behaviour-v0")
    assert "'good/behaviour-v0'" in message and "damaged or truncated" in message


# ---------------------------------------------------------------------- settings and files named
def test_one_q_sample_is_refused_naming_the_setting():
    from torchrl_wbrm.training.config import validate_config

    with pytest.raises(ValueError, match=r"^eval.q_samples must be >= 2 .* got 1\.$"):
        validate_config(tiny(eval={"q_samples": 1}))


def test_a_checkpoint_whose_config_is_a_string_is_named(tmp_path):
    run = tmp_path / "run"
    assert WBRMTrainer(tiny(), run, progress=False).run(until=15) is None
    sd = torch.load(run / "checkpoint.pt", weights_only=True)
    sd["config"] = "a string"
    torch.save(sd, run / "checkpoint.pt")
    with pytest.raises(RuntimeError) as err:
        WBRMTrainer(tiny(), run, progress=False, resume=True)
    assert str(err.value) == (f"Cannot resume: {run / 'checkpoint.pt'} is not a checkpoint this project wrote: its "
                              f"'config' is a str, not a dict.")


def test_a_read_only_run_directory_is_refused_before_anything(tmp_path, monkeypatch):
    from torchrl_wbrm.training import validation

    run = tmp_path / "run"
    assert WBRMTrainer(tiny(), run, progress=False).run(until=15) is None
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    real = os.access
    monkeypatch.setattr(validation.os, "access", lambda path, mode: Path(path) != run and real(path, mode))
    with pytest.raises(ValueError, match=f"^resume={run}: {run} cannot be written"):
        WBRMTrainer(tiny(), run, progress=False, resume=True)
    with pytest.raises(ValueError, match=f"^data_cache={run / 'cache'}: {run} cannot be written"):
        WBRMTrainer(tiny(data_cache=str(run / "cache")), tmp_path / "other", progress=False)
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before


def test_a_failed_write_names_the_file_and_the_disk_and_leaves_no_partial_file(tmp_path):
    """As ``torch.save`` on a full disk: the write fails with torch's own message; what is raised names the file,
    why and the free space, the temporary file is gone and the earlier file is whole."""
    from torchrl_wbrm.training.results import WriteFailed, atomic_write

    path = tmp_path / "checkpoint.pt"
    path.write_bytes(b"the earlier checkpoint")

    def full_disk(f):
        f.write(b"partial")
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 64 vs 0")

    with pytest.raises(WriteFailed) as err:
        atomic_write(path, full_disk, tmp=path.with_suffix(".tmp"))
    message = str(err.value)
    assert message.startswith(f"Could not write {path}: [enforce fail at inline_container.cc:672]")
    assert "MiB free of" in message and f"on the disk holding {tmp_path}" in message
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt"]
    assert path.read_bytes() == b"the earlier checkpoint"


def test_a_dataset_larger_than_the_free_space_is_refused_before_writing(tmp_path, monkeypatch):
    import shutil as shutil_module

    from torchrl_wbrm.tasks import get_task

    datasets = get_task(tiny().env).make_datasets(seed=0)
    usage = shutil_module.disk_usage(tmp_path)
    monkeypatch.setattr("torchrl_wbrm.data.datasets.shutil.disk_usage",
                        lambda path: usage._replace(free=1024))
    with pytest.raises(OSError, match=r"needs .* MiB; the disk holding it has 0.0 MiB free"):
        datasets.save(tmp_path / "cache" / "entry")
    assert not any(p.is_file() for p in (tmp_path / "cache").rglob("*"))


def test_summarise_over_a_truncated_results_json_is_one_line(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "results.json").write_text('{"status": "finished", "final": {"ret')
    proc = inprocess.run_script(ROOT / "recipes" / "summarise.py", str(tmp_path), cwd=tmp_path, env=ENV)
    assert proc.returncode == 2
    line = one_line(proc.stderr)
    assert line.startswith(f"summarise: {run / 'results.json'} is not valid JSON")


def test_the_benchmark_rerun_after_an_interruption_is_one_line(tmp_path, capsys):
    from torchrl_wbrm.data.benchmark import main

    partial = tmp_path / "D" / "benchmark" / "pendulum" / "expert-v0"
    partial.mkdir(parents=True)  # what an interrupted first run left
    with pytest.raises(SystemExit) as exit_:
        main(["--data-path", str(tmp_path / "D"), "--tasks", "pendulum"])
    assert exit_.value.code == 2
    line = one_line(capsys.readouterr().err)
    assert "'benchmark/pendulum/expert-v0' already exists" in line and "--overwrite" in line


# ---------------------------------------------------------------------- a multi-seed run stopped, then resumed
def _seed_cfg(seed: int, *extra: str):
    from torchrl_wbrm.training.config import to_config
    from studies.runs import compose_recipe_config
    from torchrl_wbrm.training.seeds import seed_config

    return seed_config(to_config(compose_recipe_config([*TINY, "seeds=[0,1]", *extra])), seed)


@pytest.mark.slow
def test_a_multi_seed_run_killed_after_its_first_seed_resumes_without_losing_it(tmp_path):
    """The state a SIGKILL leaves in a run of seeds one at a time (``q.ensemble_size=2``): seed 0 finished, seed 1
    checkpointed at step 15, the run's record in ``.hydra/``. ``resume=<run dir>`` (the printed command) keeps seed
    0's results as they were and ends seed 1 as its uninterrupted run."""
    extra = ["q.ensemble_size=2", "checkpoint_every=10"]
    run = tmp_path / "run dir"
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in [*TINY, "seeds=[0,1]", *extra]))
    WBRMTrainer(_seed_cfg(0, *extra), run / "seed0", progress=False, logger=None).run()
    assert WBRMTrainer(_seed_cfg(1, *extra), run / "seed1", progress=False, logger=None).run(until=15) is None
    seed0 = (run / "seed0" / "results.json").read_bytes()
    proc = inprocess.recipe(f"resume={run}", cwd=tmp_path, env=ENV)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (run / "seed0" / "results.json").read_bytes() == seed0
    results = json.loads((run / "results.json").read_text())
    assert results["seeds"] == [0, 1] and [r["status"] for r in results["runs"]] == ["finished", "finished"]
    alone = WBRMTrainer(_seed_cfg(1, *extra), tmp_path / "alone", progress=False, logger=None).run()
    assert results["runs"][1]["final"] == alone["final"]


def test_a_multi_seed_new_run_into_an_interrupted_one_names_the_resume(tmp_path):
    from tests.test_rundir import compose
    from torchrl_wbrm.training.hydra_guard import RunDirGuard

    run = tmp_path / "run"
    (run / "seed0").mkdir(parents=True)
    (run / "seed0" / "results.json").write_text("{}")
    with pytest.raises(SystemExit) as exit_:
        RunDirGuard().on_run_start(config=compose(*TINY, "seeds=[0,1]", f"hydra.run.dir={run}"))
    assert f"already holds a run (seed0/results.json). Continue it with resume={run}" in str(exit_.value.code)


@pytest.mark.slow
def test_ctrl_c_in_a_multi_seed_run_prints_a_quoted_resume_command_that_works(tmp_path):
    """Seeds one at a time, in a directory whose name holds a space: SIGINT stops the seed training at a step, after
    a checkpoint; the recipe exits 130 with one line, and the command it prints, run as printed, finishes the run."""
    run = tmp_path / "my runs" / "two seeds"
    overrides = [*TINY, "seeds=[0,1]", "q.ensemble_size=2", "q.steps=400", "q.eval_every=400", "checkpoint_every=40",
                 f"hydra.run.dir={run}"]
    proc = forked.popen_script(ROOT / "recipes" / "wbrm_offline.py", *overrides, cwd=tmp_path, env=ENV)
    deadline = time.time() + 180
    while not (run / "seed0" / "checkpoint.pt").is_file() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.2)
    time.sleep(0.3)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-2000:]
    last = one_line(err.split("\n", 1)[1] if err.startswith("seeds:") else err)
    assert last.startswith("SIGINT received: seed 0 stopped in stage ") and "Resume with: " in last
    command = shlex.split(last.split("Resume with: ", 1)[1].split(" (the finished seeds", 1)[0])
    assert command[-1] == f"resume={run}"
    resumed = inprocess.run_script(command[1], *command[2:], cwd=tmp_path, env=ENV)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    results = json.loads((run / "results.json").read_text())
    assert [r["status"] for r in results["runs"]] == ["finished", "finished"]
    assert all(r["final"]["step"] == 400 for r in results["runs"])


# ---------------------------------------------------------------------- logs
@pytest.mark.slow
def test_csv_logs_hold_each_step_once_after_a_resume(tmp_path):
    """Stopped at step 25 with its last checkpoint at step 20 (as a SIGKILL between two checkpoints leaves it): the
    rows of steps 21-25 are on disk; after the resume each step's row is there once, as in an uninterrupted run."""
    logger = {"backend": "csv", "log_every": 5}
    whole = tmp_path / "whole"
    WBRMTrainer(tiny(logger=logger), whole, progress=False).run()
    run = tmp_path / "run"
    trainer = WBRMTrainer(tiny(logger=logger), run, progress=False)
    trainer.run(until=25)  # a checkpoint at 20 and at the stop (25)
    shutil.copy(run / "checkpoint.pt", tmp_path / "at25.pt")
    # the checkpoint of step 20, as a kill at step 25 would leave it
    cut = WBRMTrainer(tiny(logger=logger), tmp_path / "cut20", progress=False)
    cut.run(until=20)
    shutil.copy(tmp_path / "cut20" / "checkpoint.pt", run / "checkpoint.pt")
    WBRMTrainer(tiny(logger=logger), run, progress=False, resume=True).run()

    def rows(root: Path) -> dict[str, list[str]]:
        return {str(p.relative_to(root / "logs")): p.read_text().splitlines()
                for p in sorted((root / "logs").rglob("*.csv"))}

    resumed, uninterrupted = rows(run), rows(whole)
    assert resumed.keys() == uninterrupted.keys() and resumed
    for name, lines in resumed.items():
        steps = [line.split(",")[0] for line in lines]
        assert len(steps) == len(set(steps)), (name, steps)
        assert steps == [line.split(",")[0] for line in uninterrupted[name]], name


def test_a_run_through_the_api_writes_the_recipes_logs(tmp_path):
    WBRMTrainer(tiny(logger={"backend": "csv", "log_every": 5}), tmp_path / "run", progress=False).run()
    csvs = sorted(str(p.relative_to(tmp_path / "run")) for p in (tmp_path / "run").rglob("*.csv"))
    assert "logs/wbrm_lqr_exp1_seed0/scalars/q/loss_value.csv" in csvs, csvs
    assert "logs/wbrm_lqr_exp1_seed0/scalars/eval/regret.csv" in csvs, csvs


def test_wandbs_data_and_cache_folders_go_under_the_run_directory(tmp_path, monkeypatch):
    from torchrl_wbrm.training import logging as logging_module

    for var in ("WANDB_DATA_DIR", "WANDB_CACHE_DIR"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(logging_module, "_WANDB_DIRS_SET", {})
    logging_module._wandb_dirs_under(tmp_path / "run")
    assert os.environ["WANDB_DATA_DIR"] == str(tmp_path / "run" / "wandb" / ".data")
    assert os.environ["WANDB_CACHE_DIR"] == str(tmp_path / "run" / "wandb" / ".cache")
    logging_module._wandb_dirs_under(tmp_path / "next")  # a later run moves them with it
    assert os.environ["WANDB_DATA_DIR"] == str(tmp_path / "next" / "wandb" / ".data")
    monkeypatch.setenv("WANDB_CACHE_DIR", "/the/users/own")
    logging_module._wandb_dirs_under(tmp_path / "third")
    assert os.environ["WANDB_CACHE_DIR"] == "/the/users/own"


@pytest.mark.slow
def test_a_wandb_run_writes_nothing_of_wandbs_under_home(tmp_path, monkeypatch):
    """``logger=wandb`` (offline), with plots and the results table: wandb's staging copies, cache and debug logs
    are under the run directory, nothing of wandb's under ``$HOME``."""
    import wandb

    from torchrl_wbrm.training import logging as logging_module

    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setenv("WANDB_MODE", "offline")
    for var in ("WANDB_DATA_DIR", "WANDB_CACHE_DIR", "WANDB_DIR", "WANDB_CONFIG_DIR"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(logging_module, "_WANDB_DIRS_SET", {})
    run = tmp_path / "run"
    try:
        results = WBRMTrainer(tiny(logger={"backend": "wandb", "log_every": 5}, plots=True, q={"steps": 20}), run,
                              progress=False).run()
    finally:
        if wandb.run is not None:
            wandb.finish()
    assert results["status"] == "finished"
    assert [p for p in home.rglob("*") if "wandb" in str(p.relative_to(home)).lower()] == []
    assert list((run / "wandb").glob("offline-run-*")) and (run / "wandb" / "debug.log").is_file()


def test_a_run_whose_directory_is_removed_stops_with_one_line_and_recreates_nothing(tmp_path):
    run = tmp_path / "run"
    trainer = WBRMTrainer(tiny(), run, progress=False)
    step = trainer._q_step

    def remove_at_12(i):
        if i == 12:
            shutil.rmtree(run)
        return step(i)

    trainer._q_step = remove_at_12
    with pytest.raises(FileNotFoundError) as err:
        trainer.run()
    assert str(err.value).startswith(f"The run directory {run} was removed (or replaced) while the run held it")
    assert not run.exists()


def test_a_multi_seed_resume_of_another_configs_seeds_is_refused_before_anything(tmp_path):
    from tests.test_rundir import compose
    from torchrl_wbrm.training.config import config_as_dict
    from torchrl_wbrm.training.hydra_guard import RunDirGuard

    run = tmp_path / "run"
    (run / "seed0").mkdir(parents=True)
    saved = config_as_dict(_seed_cfg(0))
    saved["q"]["lr"] = 0.5
    (run / "seed0" / "results.json").write_text(json.dumps({"status": "finished", "config": saved}))
    before = sorted(p.name for p in run.rglob("*"))
    with pytest.raises(SystemExit) as exit_:
        RunDirGuard().on_run_start(config=compose(*TINY, "seeds=[0,1]", f"resume={run}"))
    line = str(exit_.value.code)
    assert line.startswith(f"Refused (nothing was written): {run / 'seed0' / 'results.json'} holds a finished run "
                           f"with other settings: q.lr: 0.5 -> ") and "\n" not in line
    assert sorted(p.name for p in run.rglob("*")) == before


@pytest.mark.parametrize("run_dir, expected", [
    ("outputs/run_1", "python recipes/wbrm_offline.py resume=outputs/run_1"),
    ("my runs/run 1", "python recipes/wbrm_offline.py 'resume=my runs/run 1'"),
])
def test_the_printed_resume_command_is_quoted_for_the_shell(run_dir, expected):
    from torchrl_wbrm.training import stops

    assert stops.resume_command(Path(run_dir)) == expected
    assert shlex.split(expected)[-1] == f"resume={run_dir}"
    message = str(stops.RunInterrupted(signal.SIGINT, "q", 20, Path(run_dir)))
    assert message.endswith(f"Resume with: {expected}")
    started = stops.RunInterrupted(signal.SIGINT, "q", 20, Path(run_dir)).with_command("wbrm-offline")
    assert str(started).endswith("Resume with: wbrm-offline " + shlex.quote(f"resume={run_dir}"))
