"""The recipe commands (``wbrm-offline``, ``make_dataset``, the studies, the examples) as the README writes them, and
what they print and draw.

- DQN evaluates on a single episode (a batch of one), so ``paper_tables --quick`` runs every registered algorithm
  (that run: tests/test_studies.py);
- the two Minari dataset writers never collide, and an existing id or dataset is refused before any collecting;
- the resume command a run prints works exactly as printed;
- the console: no library [INFO] lines or foreign warnings by default, a config error is one line;
- the figures: each panel its own scale and y-label.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import torch

from tests import forked, inprocess
from tests.references import ROOT

#: a tiny LQR exp1 run of the recipe (seconds)
TINY = [
    "env.lqr_data.behaviour_episodes=40", "env.lqr_data.expert_episodes=20", "env.lqr_data.parallel_envs=20",
    "ratio.steps=10", "ratio.eval_every=5", "ratio.num_cells=[8,8]", "q.steps=10", "q.eval_every=5",
    "q.num_cells=[8,8]", "q.actor_num_cells=[8,8]", "eval.offline_value=false", "eval.episodes=10", "eval.train_episodes=10",
    "eval.q_samples=100",
]


def run(args: list[str], *, cwd=ROOT, timeout: int = 300, env: dict | None = None) -> subprocess.CompletedProcess:
    """``python <args>`` as a user would run it (captured, with the console's own settings); ``env`` replaces the
    environment when given."""
    full_env = {**(os.environ if env is None else env), "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1",
                "WANDB_MODE": "offline", "COLUMNS": "120"}
    return subprocess.run([sys.executable, *args], cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          env=full_env)


def recipe(*overrides: str, script: str = "wbrm_offline.py", process: bool = False, **kwargs) -> subprocess.CompletedProcess:
    """``python recipes/<script> <overrides>``: in this process (:mod:`tests.inprocess`, the same code without a new
    interpreter's imports), or with ``process`` as its own ``python`` (:func:`run`)."""
    if process:
        return run([str(ROOT / "recipes" / script), *overrides], **kwargs)
    env = {**(os.environ if kwargs.get("env") is None else kwargs["env"]), "MPLBACKEND": "Agg", "WANDB_MODE": "offline",
           "COLUMNS": "120"}
    return inprocess.run_script(ROOT / "recipes" / script, *overrides, cwd=kwargs.get("cwd", ROOT), env=env)


# ---------------------------------------------------------------------- DQN: a batch of one
def test_the_action_grid_keeps_a_batch_of_one():
    """``algo=dqn eval.train_episodes=1``: the evaluation env has batch [1] and the greedy index shape [1]; the grid
    must return one action of the box's width, [1, m], not drop the batch dimension."""
    from torchrl_wbrm.data.minari_data import OneHotActions
    from torchrl_wbrm.modules import ActionGrid

    grid = ActionGrid.from_lqr_env("exp1", 5)
    for batch in ([1], [3], [1, 1], [2, 1], []):
        index = torch.zeros(batch, dtype=torch.long)
        action = grid(index)
        assert action.shape == (*batch, 2), (batch, action.shape)
        torch.testing.assert_close(grid.index(action), index)
    one_hot = OneHotActions(3)
    assert one_hot(torch.tensor([2])).shape == (1, 3) and one_hot(torch.tensor([[2]])).shape == (1, 1, 3)
    assert one_hot(torch.tensor([2])).tolist() == [[0.0, 0.0, 1.0]]


@pytest.mark.slow
def test_dqn_evaluates_on_a_single_episode(tmp_path):
    """The reproduction from the report: ``algo=dqn eval.train_episodes=1`` (and ``eval.episodes=1``)."""
    proc = recipe("algo=dqn", *TINY, "eval.train_episodes=1", "eval.episodes=1", "logger=none", "plots=false",
                  f"hydra.run.dir={tmp_path}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["status"] == "finished" and results["algo"] == "dqn" and results["config"]["eval"]["episodes"] == 1
    assert isinstance(results["final"]["regret"], float) and results["final"]["regret"] == results["final"]["regret"]


# ---------------------------------------------------------------------- the dataset writers
TINY_LQR_DATA = ["env.lqr_data.behaviour_episodes=20", "env.lqr_data.expert_episodes=10"]


def _make_dataset_cfg(*dotlist: str):
    from omegaconf import OmegaConf

    from torchrl_wbrm.training.config import MakeDatasetConfig

    return OmegaConf.merge(OmegaConf.structured(MakeDatasetConfig), OmegaConf.from_dotlist(["format=minari", *dotlist]))


@pytest.mark.slow
def test_make_dataset_and_the_examples_never_share_an_id(tmp_path):
    """Both writers into one Minari data path, for the same env: four ids, each saying what made it."""
    from torchrl_wbrm.data.minari_examples import make_mountain_car_datasets

    proc = recipe("env=mountain_car", "format=minari", f"out={tmp_path}", "env.mountain_car_data.expert_transitions=300",
                  "env.mountain_car_data.behaviour_transitions=600", script="make_dataset.py")
    assert proc.returncode == 0, proc.stderr[-3000:]
    examples = make_mountain_car_datasets(tmp_path, expert_episodes=1, random_episodes=1, noisy_expert_episodes=1)
    assert examples["expert"] == "examples/mountain_car/expert-v0"
    ids = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*-v0"))
    assert ids == ["examples/mountain_car/behaviour-v0", "examples/mountain_car/expert-v0",
                   "make_dataset/mountain_car_seed0/behaviour-v0", "make_dataset/mountain_car_seed0/expert-v0"], ids
    assert "Minari dataset make_dataset/mountain_car_seed0/expert-v0" in proc.stdout


def test_an_existing_minari_id_is_refused_before_any_collecting(tmp_path, monkeypatch):
    from torchrl_wbrm import cli
    from torchrl_wbrm.data import minari_examples
    from torchrl_wbrm.data.minari_data import write_minari_dataset

    episode = {"observations": [[0.0, 0.0], [0.1, 0.0]], "actions": [[0.5]], "rewards": [1.0],
               "terminations": [True], "truncations": [False]}
    for dataset_id in ("make_dataset/lqr_exp1_seed0/expert-v0", "examples/mountain_car/behaviour-v0"):
        write_minari_dataset(dataset_id, [episode], data_path=tmp_path, env="MountainCarContinuous-v0")

    def no_collecting(*args, **kwargs):
        raise AssertionError("collected data before refusing")

    monkeypatch.setattr(cli, "get_task", no_collecting)
    monkeypatch.setattr(minari_examples, "collect_gym_episodes", no_collecting)
    with pytest.raises(FileExistsError) as err:
        cli._write_minari(_make_dataset_cfg("env.name=lqr_exp1"), tmp_path)
    assert "'make_dataset/lqr_exp1_seed0/expert-v0' already exists" in str(err.value)
    assert "minari_namespace=" in str(err.value) and "overwrite=true" in str(err.value)
    with pytest.raises(FileExistsError) as err:
        minari_examples.make_mountain_car_datasets(tmp_path)
    assert "'examples/mountain_car/behaviour-v0' already exists" in str(err.value) and "--namespace" in str(err.value)
    with pytest.raises(ValueError, match=r"'bad name!/expert-v0' is not a Minari dataset id.*minari_namespace="):
        cli._write_minari(_make_dataset_cfg("env.name=lqr_exp1", "minari_namespace=bad name!"), tmp_path)


def make_dataset_here(monkeypatch, capsys, *overrides: str) -> tuple[int, str, str]:
    """``make_dataset <overrides>`` in this process (the Hydra app itself): (exit status, stdout, stderr)."""
    from torchrl_wbrm.cli import make_dataset

    monkeypatch.setattr(sys, "argv", ["make_dataset", *overrides])
    try:
        make_dataset()
        code = 0
    except SystemExit as exit_:
        code = exit_.code
    out, err = capsys.readouterr()
    return code, out, err


def test_make_dataset_command_refuses_an_existing_id_in_one_line(tmp_path, monkeypatch, capsys):
    code, out, err = make_dataset_here(monkeypatch, capsys, *TINY_LQR_DATA, "format=minari", f"out={tmp_path}")
    assert code == 0, err
    again = recipe(*TINY_LQR_DATA, "format=minari", f"out={tmp_path}", script="make_dataset.py")
    assert again.returncode == 2 and again.stdout == ""
    assert again.stderr.strip().count("\n") == 0 and "Traceback" not in again.stderr
    assert "'make_dataset/lqr_exp1_seed0/expert-v0' already exists" in again.stderr
    code, out, err = make_dataset_here(monkeypatch, capsys, *TINY_LQR_DATA, "format=minari", f"out={tmp_path}",
                                       "overwrite=true")
    assert code == 0 and "replaced the old one: overwrite=true" in out, err


def test_make_dataset_refuses_an_existing_dataset_unless_overwrite(tmp_path, monkeypatch, capsys):
    """``out=ds`` twice is refused; ``overwrite=true`` replaces it; a non-empty folder holding no dataset is never
    written into; and none of that leaves anything but the dataset on disk."""
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    code, out, err = make_dataset_here(monkeypatch, capsys, *TINY_LQR_DATA, "out=ds")
    assert code == 0, err
    meta = json.loads((work / "ds" / "metadata.json").read_text())
    code, out, err = make_dataset_here(monkeypatch, capsys, *TINY_LQR_DATA, "seed=1", "out=ds")
    assert code == 2 and "already holds a dataset" in err and "overwrite=true" in err and out == ""
    assert err.strip().count("\n") == 0
    assert json.loads((work / "ds" / "metadata.json").read_text()) == meta  # untouched
    code, out, err = make_dataset_here(monkeypatch, capsys, *TINY_LQR_DATA, "seed=1", "out=ds", "overwrite=true")
    assert code == 0 and "replaced the dataset there" in out, err
    new_meta = json.loads((work / "ds" / "metadata.json").read_text())
    assert new_meta["files"] != meta["files"]  # seed 1's data, not seed 0's
    (work / "mine").mkdir()
    (work / "mine" / "notes.txt").write_text("the user's own")
    for extra in ([], ["overwrite=true"]):
        code, out, err = make_dataset_here(monkeypatch, capsys, *TINY_LQR_DATA, "out=mine", *extra)
        assert code == 2 and "holds no dataset (notes.txt)" in err, err
    assert sorted(p.name for p in (work / "mine").iterdir()) == ["notes.txt"]
    assert sorted(p.name for p in work.iterdir()) == ["ds", "mine"]  # no outputs/ folder, no .log


# ---------------------------------------------------------------------- the printed resume command
def test_resume_restores_the_runs_own_overrides(tmp_path):
    from torchrl_wbrm.cli import with_run_overrides

    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "overrides.yaml").write_text("- env=lqr_exp3\n- q.lr=0.003\n- seed=2\n- overwrite=true\n")
    assert with_run_overrides([f"resume={run}"]) == ["env=lqr_exp3", "q.lr=0.003", "seed=2", f"resume={run}"]
    # the command line wins over the record, and a second resume (its record rewritten with them) finds them again
    args = with_run_overrides([f"resume={run}", "q.steps=40"])
    assert args == ["env=lqr_exp3", "q.lr=0.003", "seed=2", f"resume={run}", "q.steps=40"]
    (run / ".hydra" / "overrides.yaml").write_text("".join(f"- {a}\n" for a in args))
    assert with_run_overrides([f"resume={run}"]) == ["env=lqr_exp3", "q.lr=0.003", "seed=2", "q.steps=40",
                                                     f"resume={run}"]
    assert with_run_overrides(["q.lr=0.1"]) == ["q.lr=0.1"]  # not a resume
    assert with_run_overrides([f"resume={tmp_path / 'none'}"]) == [f"resume={tmp_path / 'none'}"]


@pytest.mark.slow
def test_the_printed_resume_command_works_as_printed(tmp_path):
    """A run started with overrides (and the default dated run directory) is interrupted with SIGINT: it exits 130
    with one line naming the stage and the step of its checkpoint, and the command it prints is run exactly as
    printed and finishes the run with the overrides it started with."""
    import shlex
    import signal
    import time

    overrides = [*TINY, "q.steps=400", "q.eval_every=400", "checkpoint_every=40", "q.lr=0.002", "seed=3",
                 "logger=none", "plots=false"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg",
           "PATH": f"{os.path.dirname(sys.executable)}{os.pathsep}{os.environ.get('PATH', '')}"}
    # a process of its own, for the signal (:mod:`tests.forked`); the resume below is the printed command itself
    proc = forked.popen_script(ROOT / "recipes" / "wbrm_offline.py", *overrides, cwd=tmp_path, env=env)
    deadline = time.time() + 180
    while not list(tmp_path.glob("outputs/wbrm_offline/lqr_exp1/*/checkpoint.pt")) and time.time() < deadline \
            and proc.poll() is None:
        time.sleep(0.2)
    time.sleep(0.3)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err[-2000:]
    last = err.strip().splitlines()[-1]  # one line, naming the stage and step its checkpoint holds
    assert last.startswith("SIGINT received: stopped in stage 'q' at step ") and "Traceback" not in err, err[-2000:]
    (checkpoint,) = tmp_path.glob("outputs/wbrm_offline/lqr_exp1/*/checkpoint.pt")
    step = torch.load(checkpoint, weights_only=True)["state"]["step"]
    assert step > 0 and f"at step {step}," in last, (step, last)
    command = last.split("Resume with: ", 1)[1]
    assert command.startswith(f"python {ROOT / 'recipes' / 'wbrm_offline.py'} resume=") and "_seed3" in command
    resumed = subprocess.run(shlex.split(command), cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    (run_dir,) = tmp_path.glob("outputs/wbrm_offline/lqr_exp1/*_seed3")
    results = json.loads((run_dir / "results.json").read_text())
    assert results["status"] == "finished" and results["seed"] == 3 and results["config"]["q"]["lr"] == 0.002
    assert results["final"]["step"] == 400
    assert len(list(tmp_path.glob("outputs/wbrm_offline/lqr_exp1/*"))) == 1  # no stray directory for the resume


@pytest.mark.parametrize("argv0, command", [
    ("/venv/bin/wbrm-offline", "wbrm-offline"),
    ("/site-packages/torchrl_wbrm/__main__.py", "python -m torchrl_wbrm"),
    ("recipes/wbrm_offline.py", "python recipes/wbrm_offline.py"),
])
def test_the_resume_command_names_how_the_recipe_was_started(monkeypatch, argv0, command):
    from torchrl_wbrm.cli import recipe_command

    monkeypatch.setattr(sys, "argv", [argv0, "seed=1"])
    assert recipe_command() == command


# ---------------------------------------------------------------------- LQR: the exact return's refusal
def test_policy_return_refusal_names_the_action_noise():
    """``policy_return(0.5 K, 0.5)`` on exp1 (a 2-D system): the clipped figure is refused because of the action
    noise, not the state dimension; without noise, or unclipped, it is given."""
    import math

    from torchrl_wbrm.envs import LQREnv

    env = LQREnv("exp1")
    gain = 0.5 * env.riccati()[1]
    with pytest.raises(NotImplementedError) as err:
        env.policy_return(gain, 0.5)
    message = str(err.value)
    assert "action noise" in message and "action_noise_std" in message and "clipped=False" in message
    assert "state dimension" not in message.split(":")[1]
    assert math.isfinite(env.policy_return(gain, 0.5, clipped=False)) and math.isfinite(env.policy_return(gain, 0.0))


# ---------------------------------------------------------------------- the console
def test_no_library_info_lines_from_the_python_api():
    """A replay buffer filled through the Python API (as the examples do) prints no torchrl ``[INFO]`` line, even
    with torchrl imported first; ``TORCHRL_WBRM_VERBOSE=1`` brings them back."""
    fill = ("from tensordict import TensorDict\nimport torch\nfrom torchrl.data import LazyTensorStorage, ReplayBuffer\n"
            "ReplayBuffer(storage=LazyTensorStorage(10)).extend(TensorDict({'a': torch.zeros(4)}, [4]))\n")
    env = {k: v for k, v in os.environ.items() if k not in ("RL_LOGGING_LEVEL", "TORCHRL_WBRM_VERBOSE")}
    quiet = run(["-c", "import torchrl\nimport torchrl_wbrm.data\n" + fill], env=env)
    assert quiet.returncode == 0, quiet.stderr[-2000:]
    assert "[INFO]" not in quiet.stdout + quiet.stderr and quiet.stderr == "", quiet.stdout + quiet.stderr
    verbose = run(["-c", "import torchrl_wbrm.data\n" + fill], env={**env, "TORCHRL_WBRM_VERBOSE": "1"})
    assert "[torchrl][INFO]" in verbose.stdout + verbose.stderr


def test_bc_builds_without_torchrls_annotation_warning(tmp_path):
    """``algo=bc``: torchrl's ``BCLoss`` warns about an annotation it lacks (900 characters); not on our console."""
    import warnings

    from tests.references import compose_recipe
    from torchrl_wbrm.training import WBRMTrainer

    cfg = compose_recipe("algo=bc", *TINY, "logger=none", "plots=false")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        WBRMTrainer(cfg, tmp_path, progress=False).run()
    assert not [w for w in caught if "wasn't part of the annotations" in str(w.message)]


@pytest.mark.parametrize("figures", [
    {"loss_density_ratio": -2.01234, "density_ratio_behaviour_mean": 1.0, "density_ratio_expert_mean": 3.2,
     "density_ratio_min": 0.01, "density_ratio_max": 12.3, "density_ratio_ess": 3012.3, "normalisation_penalty": 0.1},
    {"loss_value": 0.0231234, "td_error_mean": -0.00123, "td_error_abs_mean": 0.1234, "q_mean": 84.2312,
     "target_value_mean": 84.1, "weight_mean": 1.0, "weight_ess": 1640.2, "expert_bc_loss": 0.5, "loss_actor": -99.12},
    {"loss_actor": -12.3456, "loss_actor_bc": 0.123456, "loss_qvalue": 123.456, "loss_cql": 45.678,
     "loss_alpha": -0.0012345, "alpha": 0.5, "entropy": -1.2345},
])
def test_the_progress_bar_keeps_its_figures_whole_at_120_columns(figures):
    from tqdm import tqdm

    from torchrl_wbrm.training.logging import progress_postfix

    postfix = progress_postfix(figures)
    assert postfix.split("=")[0] in ("loss", "loss_q") and len(postfix) <= 44
    line = tqdm.format_meter(4500, 10000, 37.2, ncols=120, prefix="q", postfix=postfix)
    assert len(line) <= 120 and line.rstrip().endswith(postfix + "]"), line
    assert "|" in line.split(postfix)[0]  # the bar itself is still drawn


def test_a_config_error_is_one_line(tmp_path):
    """``device=cuda`` without CUDA (or another refused setting): one line on stderr, no traceback, non-zero exit,
    and nothing written."""
    import torch as _torch

    bad = "device=cuda" if not _torch.cuda.is_available() else "ratio.bounds=[0.5]"
    proc = recipe(bad, f"hydra.run.dir={tmp_path / 'run'}")
    assert proc.returncode != 0 and "Traceback" not in proc.stderr and proc.stdout == ""
    assert len(proc.stderr.strip().splitlines()) == 1 and ("device" in proc.stderr or "ratio.bounds" in proc.stderr)
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_the_recipe_writes_no_empty_log(tmp_path):
    # a process of its own (:mod:`tests.forked`): a library's INFO line goes to a handler bound to the real stream,
    # which only a process shows
    env = {**os.environ, "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1", "WANDB_MODE": "offline", "COLUMNS": "120"}
    proc = forked.run_forked(ROOT / "recipes" / "wbrm_offline.py", *TINY, "logger=none", "plots=false",
                             f"hydra.run.dir={tmp_path}", cwd=ROOT, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert not [p.name for p in tmp_path.glob("*.log") if p.stat().st_size == 0]
    assert "[INFO]" not in proc.stdout + proc.stderr


# ---------------------------------------------------------------------- the studies' smoke runs
class _Ran(Exception):
    pass


@pytest.mark.parametrize("study", ["paper_tables", "weighting_study", "ablations", "convergence_study",
                                   "q_accuracy_study"])
def test_a_quick_study_never_writes_into_the_full_ones_folder(study, monkeypatch):
    """``--quick`` and the full study default to different folders: a smoke run's finished runs (another budget)
    would otherwise be found, and refused, by the full study."""
    import importlib

    from studies import runs

    monkeypatch.syspath_prepend(str(ROOT / "recipes"))
    module = importlib.import_module(study)
    outs = []

    def record(cells, seeds, budget, out, **kwargs):
        outs.append(str(out))
        raise _Ran

    monkeypatch.setattr(runs, "run_cells", record)
    for argv, expected in (([], f"results/{study}"), (["--quick"], f"results/{study}_quick")):
        monkeypatch.setattr(sys, "argv", [study, *argv])
        with pytest.raises(_Ran):
            module.main()
        assert outs[-1] == expected


@pytest.mark.slow
def test_the_examples_command_is_quiet(tmp_path):
    """``python -m torchrl_wbrm.data.minari_examples`` (a README command): its two lines, nothing on stderr (no
    runpy warning about the module being imported before it runs, no library INFO line)."""
    proc = run(["-m", "torchrl_wbrm.data.minari_examples", "--env", "cartpole", "--data-path", str(tmp_path)])
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr[-2000:]
    assert proc.stdout.splitlines() == [f"expert:    {tmp_path}/examples/cartpole/expert-v0",
                                        f"behaviour: {tmp_path}/examples/cartpole/behaviour-v0"]


# ---------------------------------------------------------------------- one preparation of the config per run
@pytest.mark.parametrize("seeds", [None, [0, 1]])
def test_a_recipe_run_prepares_its_config_once(tmp_path, monkeypatch, seeds):
    """The recipe merges, resolves and validates its config once and builds its env's task once (counted): the Hydra
    callback prepares them (``prepare_config``) and hands them to the run and its trainer. With ``seeds=[0,1]`` the
    config is validated once for both seeds; each seed's trainer runs ``PreparedConfig.for_seed`` and builds only its
    own task (it holds the seed's data)."""
    from collections import Counter

    from torchrl_wbrm import cli
    from torchrl_wbrm.tasks.base import Task
    from torchrl_wbrm.training import config as config_module

    counts = Counter()
    init, choices = Task.__init__, config_module._choices

    def counting_init(self, env):
        counts["tasks built"] += 1
        init(self, env)

    def counting_choices():  # read once per validation
        counts["validations"] += 1
        return choices()

    monkeypatch.setattr(Task, "__init__", counting_init)
    monkeypatch.setattr(config_module, "_choices", counting_choices)
    extra = [] if seeds is None else [f"seeds=[{','.join(map(str, seeds))}]"]
    monkeypatch.setattr(sys, "argv", ["wbrm-offline", *TINY, "logger=none", "plots=false", "threads=1", *extra,
                                      f"hydra.run.dir={tmp_path / 'run'}"])
    cli.wbrm_offline()
    results = json.loads((tmp_path / "run" / "results.json").read_text())
    assert results["status"] == "finished"
    if seeds is None:
        assert counts == {"tasks built": 1, "validations": 1}
    else:
        assert [r["seed"] for r in results["runs"]] == seeds
        assert counts == {"tasks built": 3, "validations": 1}  # the run's task, then one per seed
