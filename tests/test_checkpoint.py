"""Reading a checkpoint never runs code: ``checkpoint.pt`` is read with ``torch.load(weights_only=True)``.

A crafted pickle in a run directory that otherwise looks like a real run is refused, in one line naming the file,
by the trainer and by the recipe, and what its unpickling would do (create a marker file) never happens; so is a
run record (``.hydra/overrides.yaml``) that names anything but the recipe's own settings. A real
checkpoint (every algo's) holds only what such a load accepts, and resumes exactly; so does one whose NumPy random
state is the array ``np.random.get_state()`` returns.
"""
from __future__ import annotations

import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.references import tiny_lqr_config
from torchrl_wbrm.training import WBRMTrainer

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
    proc = subprocess.run([sys.executable, str(ROOT / "recipes" / "wbrm_offline.py"), f"resume={path.parent}"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
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
    proc = subprocess.run([sys.executable, str(ROOT / "recipes" / "wbrm_offline.py"), f"resume={run}"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
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


def test_a_checkpoint_holding_numpys_random_state_array_resumes_exactly(tmp_path):
    """The NumPy state as ``np.random.get_state()`` returns it (an ``uint32`` array) is read too, and restored."""
    cut = WBRMTrainer(tiny(), tmp_path, progress=False)
    assert cut.run(until=15) is None
    path = tmp_path / "checkpoint.pt"
    sd = torch.load(path, weights_only=True)
    state = sd["rng"]["numpy"]
    sd["rng"]["numpy"] = (state["name"], state["keys"].numpy().astype(np.uint32), state["pos"], state["has_gauss"],
                          state["cached_gaussian"])
    torch.save(sd, path)
    assert torch.serialization.get_unsafe_globals_in_checkpoint(path)  # NumPy's array, not a plain tensor
    resumed = WBRMTrainer(tiny(), tmp_path, progress=False, resume=True)
    assert resumed.state == {"stage": "q", "step": 15}
    expected = np.random.RandomState()
    expected.set_state(sd["rng"]["numpy"])
    assert np.random.random() == expected.random_sample()
