"""Checkpoints: reading one never runs code (``checkpoint.pt`` is read with ``torch.load(weights_only=True)``), and
a run killed at any point resumes to the uninterrupted run's figures.

A crafted pickle in a run directory that otherwise looks like a real run is refused, in one line naming the file,
by the trainer and by the recipe, and what its unpickling would do (create a marker file) never happens; so is a
run record (``.hydra/overrides.yaml``) that names anything but the recipe's own settings. A real
checkpoint (every algo's) holds only what such a load accepts, and resumes exactly; one holding a NumPy array (its
random state as ``np.random.get_state()`` returns it) is refused.

A run killed with SIGKILL (nothing caught, nothing flushed) and resumed with the recipe's resume command ends with
the figures of the uninterrupted run, exactly.

The kill points are made deterministic by the writers' test hook (``TORCHRL_WBRM_TEST_PAUSE_AT``,
:func:`torchrl_wbrm.training.results.pause_for_test`): the recipe stops at the named point, says so on stderr, and
waits to be killed. Points: during stage 1 and during stage 2 (at a step), while a checkpoint is being written (its
new content on disk in the temporary file, not yet renamed), and while ``results.json`` is being written.
"""
from __future__ import annotations

import json
import os
import pickle
import shutil
import signal
import threading
from pathlib import Path

import numpy as np
import pytest
import torch

from tests import forked, inprocess
from tests.references import tiny_lqr_config
from torchrl_wbrm.training import WBRMTrainer
from torchrl_wbrm.training.results import TEST_PAUSE_ENV

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.usefixtures("single_thread")  # tests/conftest.py: one torch thread per test


def tiny(**overrides):
    return tiny_lqr_config({"checkpoint_every": 10}, **overrides)


class _Touch:
    """Unpickled, it creates ``marker`` (``pathlib.Path.touch``)."""

    def __init__(self, marker: Path) -> None:
        self.marker = Path(marker)

    def __reduce__(self):
        return Path.touch, (self.marker,)


class _Shell:
    """Unpickled, it runs ``touch marker`` in a shell (``os.system``)."""

    def __init__(self, marker: Path) -> None:
        self.marker = Path(marker)

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A finished tiny run: its directory (checkpoint, results, history)."""
    run_dir = tmp_path_factory.mktemp("finished")
    WBRMTrainer(tiny(), run_dir, progress=False).run()
    return run_dir


def _crafted(finished: Path, run_dir: Path, marker: Path, form: str) -> Path:
    """A copy of ``finished`` whose ``checkpoint.pt`` is a crafted pickle: the real checkpoint with a payload inside
    (``torch.save``), or a plain pickle of a dict with every checkpoint key (``pickle.dump``, the legacy format)."""
    shutil.copytree(finished, run_dir)
    path = run_dir / "checkpoint.pt"
    sd = torch.load(path, weights_only=True)
    if form == "torch_save":
        sd["history"].append({"stage": "q", "step": 1, "note": _Touch(marker)})
        torch.save(sd, path)
    else:
        with open(path, "wb") as f:
            pickle.dump({**{k: None for k in sd}, "state": _Shell(marker)}, f, protocol=4)
    return path


def test_the_crafted_payloads_do_run_when_unpickled_without_restriction(tmp_path):
    """The payloads are live: a plain unpickling creates the marker (so the refusal tests below can fail)."""
    for payload in (_Touch(tmp_path / "a"), _Shell(tmp_path / "b")):
        pickle.loads(pickle.dumps(payload))
    assert (tmp_path / "a").exists() and (tmp_path / "b").exists()


@pytest.mark.parametrize("form", ["torch_save", "pickle_dump"])
def test_a_crafted_checkpoint_is_refused_by_the_trainer_and_runs_nothing(finished, tmp_path, form):
    marker = tmp_path / "marker"
    path = _crafted(finished, tmp_path / "run", marker, form)
    before = {p.name: p.read_bytes() for p in path.parent.iterdir() if p.is_file()}
    with pytest.raises(RuntimeError) as err:
        WBRMTrainer(tiny(), path.parent, progress=False, resume=True)
    message = str(err.value)
    assert message.startswith(f"Cannot resume: {path} is not a checkpoint this project wrote: it ")
    assert "nothing in it ran" in message and "\n" not in message
    named = ("pathlib.Path", "builtins.getattr") if form == "torch_save" else (f"{os.system.__module__}.system",)
    assert all(name in message.split(" when read")[0] for name in named)
    assert not marker.exists()
    assert {p.name: p.read_bytes() for p in path.parent.iterdir() if p.is_file()} == before


def test_a_crafted_checkpoint_is_refused_by_the_recipe_in_one_line(finished, tmp_path):
    marker = tmp_path / "marker"
    path = _crafted(finished, tmp_path / "run", marker, "torch_save")
    proc = inprocess.recipe(f"resume={path.parent}", cwd=tmp_path, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode != 0
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr[-3000:]
    assert f"{path} is not a checkpoint this project wrote" in lines[0] and "nothing in it ran" in lines[0]
    assert "Traceback" not in proc.stderr + proc.stdout
    assert not marker.exists()
    assert not (tmp_path / "outputs").exists()  # a refused command writes nothing


@pytest.mark.parametrize("override", [
    "+hydra.callbacks.payload={_target_:builtins.open,_args_:['MARKER','w']}",
    "++hydra.callbacks.payload._target_=builtins.open",
    "~hydra.callbacks.run_dir_guard",
])
def test_a_run_record_naming_more_than_the_recipes_settings_is_refused(finished, tmp_path, override):
    """``resume=X`` re-applies ``X/.hydra/overrides.yaml``: an entry Hydra would instantiate (a callback's
    ``_target_``, here ``builtins.open(MARKER, 'w')``, which creates the file) or that removes the run's guard is
    refused in one line before Hydra sees it, and nothing is created."""
    marker = tmp_path / "marker"
    run = tmp_path / "run"
    shutil.copytree(finished, run)
    (run / ".hydra").mkdir()
    record = run / ".hydra" / "overrides.yaml"
    record.write_text(f'- "{override.replace("MARKER", str(marker))}"\n- q.steps=40\n')
    proc = inprocess.recipe(f"resume={run}", cwd=tmp_path, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode != 0
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert f"Cannot resume: {record} holds the override " in lines[0] and "not a setting of this recipe" in lines[0]
    assert not marker.exists()


def test_a_damaged_checkpoint_is_still_named_as_damaged(finished, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(finished, run)
    path = run / "checkpoint.pt"
    os.truncate(path, path.stat().st_size // 2)
    with pytest.raises(RuntimeError, match=rf"^Cannot resume: {path} is corrupted or not a checkpoint \(") as err:
        WBRMTrainer(tiny(), run, progress=False, resume=True)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("algo", ["wbrm", "td3bc", "iql", "cql", "mabo", "dqn"])
def test_every_algos_checkpoint_holds_only_what_a_weights_only_load_accepts(tmp_path, algo):
    overrides = {"algo": algo, "q": {"steps": 4, "eval_every": 4}, "ratio": {"steps": 4, "eval_every": 2}}
    trainer = WBRMTrainer(tiny(**overrides), tmp_path, progress=False)
    trainer.run(until=2)
    assert torch.serialization.get_unsafe_globals_in_checkpoint(tmp_path / "checkpoint.pt") == []
    assert torch.load(tmp_path / "checkpoint.pt", weights_only=True)["state"]["stage"] == "q"


def test_a_resumed_checkpoint_ends_as_the_uninterrupted_run(tmp_path):
    whole = WBRMTrainer(tiny(), tmp_path / "whole", progress=False).run()
    cut = WBRMTrainer(tiny(), tmp_path / "cut", progress=False)
    assert cut.run(until=15) is None
    resumed = WBRMTrainer(tiny(), tmp_path / "cut", progress=False, resume=True).run()
    assert resumed["final"] == whole["final"] and resumed["ratio"] == whole["ratio"]


def test_a_checkpoint_holding_a_numpy_array_is_refused_in_one_line_and_nothing_in_it_is_built(tmp_path):
    """The random states are saved as tensors and primitives only; a checkpoint holding a NumPy array (here NumPy's
    random state as ``np.random.get_state()`` returns it) names a global, so it is refused unread, in one line."""
    cut = WBRMTrainer(tiny(), tmp_path, progress=False)
    assert cut.run(until=15) is None
    path = tmp_path / "checkpoint.pt"
    sd = torch.load(path, weights_only=True)
    state = sd["rng"]["numpy"]
    assert isinstance(state["keys"], torch.Tensor)  # what a run writes: a tensor
    sd["rng"]["numpy"] = (state["name"], state["keys"].numpy().astype(np.uint32), state["pos"], state["has_gauss"],
                          state["cached_gaussian"])
    torch.save(sd, path)
    with pytest.raises(RuntimeError) as err:
        WBRMTrainer(tiny(), tmp_path, progress=False, resume=True)
    message = str(err.value)
    assert "\n" not in message and str(path) in message and "not a checkpoint this project wrote" in message
    assert "_reconstruct" in message  # the global it would import, named


# ---------------------------------------------------------------------- SIGKILL, then the resume command
#: the tiny LQR run (tests/references.py's TINY_LQR) as recipe overrides, a checkpoint every 10 steps: checkpoints
#: are written at stage-1 steps 10 and 20, at the end of stage 1, at stage-2 steps 10, 20 and 30, after stage 2 and
#: when the run is done
OVERRIDES = [
    "env.lqr_data.behaviour_episodes=40", "env.lqr_data.expert_episodes=20", "env.lqr_data.parallel_envs=20",
    "ratio.steps=30", "ratio.batch_size=64", "ratio.eval_every=10", "ratio.num_cells=[16,16]",
    "q.steps=40", "q.batch_size=32", "q.eval_every=20", "q.num_cells=[16,16]", "q.actor_num_cells=[16,16]",
    "eval.offline_value=false", "eval.episodes=50", "eval.train_episodes=20", "eval.q_samples=300", "logger=none", "plots=false",
    "checkpoint_every=10", "threads=1",
]
#: what differs between two runs of one config: wall-clock times
TIMES = ("wall_seconds", "data_seconds", "compile_seconds")
RECIPE = ROOT / "recipes" / "wbrm_offline.py"


def _env(pause: str | None = None) -> dict:
    env = {k: v for k, v in os.environ.items() if k != TEST_PAUSE_ENV}
    env["OMP_NUM_THREADS"] = "1"
    if pause is not None:
        env[TEST_PAUSE_ENV] = pause
    return env


def _figures(run_dir: Path) -> dict:
    """``results.json`` (but its wall-clock times, and ``config.resume``, which names the directory a resumed run
    continued) and ``history.json``."""
    results = json.loads((run_dir / "results.json").read_text())
    results["config"].pop("resume")
    return {"results": {k: v for k, v in results.items() if k not in TIMES},
            "history": json.loads((run_dir / "history.json").read_text())}


def _run_until_paused(overrides: list[str], pause: str, cwd: Path, timeout: float = 300.0) -> forked.ForkedProcess:
    """Start the recipe with ``overrides`` in a process of its own (:mod:`tests.forked`) with the hook set to
    ``pause``; return once it says it is paused there (then it waits)."""
    proc = forked.popen_script(RECIPE, *overrides, cwd=cwd, env=_env(pause), stdout=False)
    paused, lines = threading.Event(), []

    def read():
        for line in proc.stderr:
            lines.append(line)
            if line.strip() == f"{TEST_PAUSE_ENV}: paused at {pause}":
                paused.set()

    threading.Thread(target=read, daemon=True).start()
    if not paused.wait(timeout):
        proc.kill()
        proc.wait()
        pytest.fail(f"the run never paused at {pause} (exit code {proc.returncode}): {''.join(lines)[-3000:]}")
    return proc


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The run without interruption (in this process, :mod:`tests.inprocess`): its figures."""
    root = tmp_path_factory.mktemp("uninterrupted")
    proc = inprocess.recipe(*OVERRIDES, f"hydra.run.dir={root / 'run'}", cwd=root, env=_env())
    assert proc.returncode == 0, proc.stderr[-3000:]
    return _figures(root / "run")


@pytest.mark.slow
@pytest.mark.parametrize("point, written", [
    ("ratio:15", "the checkpoint of stage-1 step 10"),
    ("checkpoint.pt:2", "the checkpoint of stage-1 step 10: the one of step 20 is in checkpoint.tmp, not renamed"),
    ("q:25", "the checkpoint of stage-2 step 20"),
    ("checkpoint.pt:5", "the checkpoint of stage-2 step 10: the one of step 20 is in checkpoint.tmp, not renamed"),
    ("results.json:1", "the checkpoint of the finished run; results.json is in results.json.tmp, not renamed"),
])
def test_sigkill_then_resume_gives_the_uninterrupted_figures(uninterrupted, tmp_path, point, written):
    run_dir = tmp_path / "run"
    proc = _run_until_paused([*OVERRIDES, f"hydra.run.dir={run_dir}"], point, tmp_path)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    assert not (run_dir / "results.json").exists()  # never a half-written one
    state = torch.load(run_dir / "checkpoint.pt", weights_only=True)["state"]  # complete: it reads
    expected = {"ratio:15": {"stage": "ratio", "step": 10}, "checkpoint.pt:2": {"stage": "ratio", "step": 10},
                "q:25": {"stage": "q", "step": 20}, "checkpoint.pt:5": {"stage": "q", "step": 10},
                "results.json:1": {"stage": "done", "step": 40}}[point]
    assert state == expected, written

    # the command a user types (run in this process): the run's overrides come back
    resumed = inprocess.recipe(f"resume={run_dir}", cwd=tmp_path, env=_env())
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert _figures(run_dir) == uninterrupted


def test_the_cuda_generators_are_saved_only_where_cuda_was_used_and_restored_only_where_it_exists():
    from torchrl_wbrm.training import get_rng_state, set_rng_state

    state = get_rng_state()
    assert ("cuda" in state) == torch.cuda.is_initialized()
    set_rng_state(state)  # what this process saved, it restores
    if torch.cuda.is_available():
        return
    state["cuda"] = [torch.zeros(16, dtype=torch.uint8)]  # saved on a CUDA machine, resumed on this one
    with pytest.raises(RuntimeError, match=r"^Cannot restore the random state of 1 CUDA device\(s\) saved with this "
                                           r"checkpoint: this machine has 0\.$"):
        set_rng_state(state)
