"""Run directories: one run per directory (an exclusive claim), fresh dated directories, refused commands that change
nothing on disk (Hydra's ``.hydra/`` record included), ``overwrite=true`` without old logs, resumes without stray
directories.

The recipe's checks run in a Hydra callback (:class:`~torchrl_wbrm.training.hydra_guard.RunDirGuard`) before Hydra writes
anything; most tests call it on a composed config, two run the recipe itself in subprocesses.
"""
from __future__ import annotations

import copy
import hashlib
import os
from pathlib import Path

import pytest
import torch
from omegaconf import open_dict

from tests import forked
from tests.references import tiny_lqr_config
from torchrl_wbrm.training import WBRMTrainer
from torchrl_wbrm.training.config import WBRMConfig
from torchrl_wbrm.training.hydra_guard import RunDirGuard
from torchrl_wbrm.training.rundir import RunDirInUse, claim_run_dir

ROOT = Path(__file__).resolve().parents[1]
#: the recipe's tiny budget (the issue's, with tiny data and networks)
TINY = [
    "ratio.steps=20", "q.steps=40", "q.eval_every=20", "eval.offline_value=false", "eval.episodes=50", "eval.train_episodes=20", "logger=none",
    "plots=false", "env.lqr_data.behaviour_episodes=40", "env.lqr_data.expert_episodes=20",
    "env.lqr_data.parallel_envs=20", "q.num_cells=[16,16]", "q.actor_num_cells=[16,16]", "eval.q_samples=300",
    "ratio.num_cells=[16,16]",
]


pytestmark = pytest.mark.usefixtures("single_thread")  # tests/conftest.py: one torch thread per test


def tiny(**overrides) -> WBRMConfig:
    """The tiny LQR run (tests/references.py), with this file's own settings."""
    return tiny_lqr_config({"ratio": {"steps": 20}, "q": {"steps": 20}}, **overrides)


def snapshot(root: Path) -> dict[str, tuple[int, str, int]]:
    return {
        str(p.relative_to(root)): (p.stat().st_size, hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
        for p in sorted(Path(root).rglob("*")) if p.is_file()
    }


def compose(*overrides: str, hydra: bool = True):
    """The recipe's config with its ``hydra`` node, as Hydra hands it to the callbacks (``hydra=False``: without)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from torchrl_wbrm.training.config import register_configs
    from torchrl_wbrm.configs import CONFIG_DIR

    register_configs()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return hydra_compose("wbrm_offline", overrides=list(overrides), return_hydra_config=hydra)


def guard(config) -> Path:
    """Run the callback's checks; the run directory it settled on (its claim released again)."""
    claim = RunDirGuard.check(config)
    claim.release()
    return Path(str(config.hydra.run.dir))


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A finished run of the recipe's config with :data:`TINY`: its directory."""
    run_dir = tmp_path_factory.mktemp("finished")
    WBRMTrainer(compose(*TINY, hydra=False), run_dir, progress=False).run()
    return run_dir


# ---------------------------------------------------------------------- one run per directory
def test_two_claims_of_one_directory_are_refused(tmp_path):
    first = claim_run_dir(tmp_path)
    with pytest.raises(RunDirInUse, match=rf"{tmp_path} is in use by another run"):
        claim_run_dir(tmp_path)
    first.release()
    claim_run_dir(tmp_path).release()  # free again
    assert list(tmp_path.iterdir()) == []  # the claim writes nothing


def test_a_second_trainer_on_a_directory_in_use_is_refused(tmp_path):
    trainer = WBRMTrainer(tiny(), tmp_path, progress=False)
    before = snapshot(tmp_path)
    with pytest.raises(RunDirInUse, match="in use by another run"):
        WBRMTrainer(tiny(q={"lr": 3e-3}), tmp_path, progress=False)
    assert snapshot(tmp_path) == before
    assert trainer.run()["config"]["q"]["lr"] == 1e-3
    # the run has ended: the directory is free, and now holds a run
    with pytest.raises(FileExistsError, match="already holds a run"):
        WBRMTrainer(tiny(q={"lr": 3e-3}), tmp_path, progress=False)


def test_two_runs_started_in_one_second_get_directories_of_their_own(tmp_path):
    config = compose(*TINY)
    with open_dict(config):
        # a dated pattern both runs resolve alike (as two runs started in one second do)
        config.hydra.run.dir = str(tmp_path / "outputs" / "${now:%Y}_seed${seed}")
    first, second = guard(copy.deepcopy(config)), guard(copy.deepcopy(config))
    assert first != second and second.name == f"{first.name}_1"
    assert first.is_dir() and second.is_dir()


def test_two_recipe_runs_into_one_directory_one_is_refused(tmp_path):
    """Both started at once into one directory: one finishes, the other is refused; the directory holds the
    winner's checkpoint, results and Hydra record, all of one run."""
    run_dir = tmp_path / "X"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    # two processes of their own (:mod:`tests.forked`), started together
    procs = {lr: forked.popen_script(ROOT / "recipes" / "wbrm_offline.py", *TINY, f"q.lr={lr}",
                                     f"hydra.run.dir={run_dir}", cwd=tmp_path, env=env)
             for lr in (0.001, 0.003)}
    outcome = {lr: (proc.returncode, err) for lr, proc in procs.items() for _, err in [proc.communicate(timeout=300)]}
    codes = sorted(code for code, _ in outcome.values())
    assert codes == [0, 1], outcome
    (winner,) = [lr for lr, (code, _) in outcome.items() if code == 0]
    (loser,) = [lr for lr, (code, _) in outcome.items() if code == 1]
    err = outcome[loser][1]
    assert "in use by another run" in err or "already holds a run" in err, err
    import json

    results = json.loads((run_dir / "results.json").read_text())
    assert results["config"]["q"]["lr"] == winner
    assert torch.load(run_dir / "checkpoint.pt", weights_only=True)["config"]["q"]["lr"] == winner
    assert f"q.lr={winner}" in (run_dir / ".hydra" / "overrides.yaml").read_text()


# ---------------------------------------------------------------------- refused commands change nothing
def test_refused_new_run_and_resume_leave_the_directory_and_its_record_alone(finished):
    hydra = finished / ".hydra"
    hydra.mkdir(exist_ok=True)
    (hydra / "overrides.yaml").write_text("- q.lr=0.001\n")
    before = snapshot(finished)
    for overrides in ([f"hydra.run.dir={finished}"],  # a new run into a run directory
                      [f"resume={finished}", "q.lr=0.003"],  # a resume with a changed setting
                      [f"resume={finished}", f"hydra.run.dir={finished}", "q.lr=0.003"]):
        with pytest.raises(SystemExit, match="Refused \\(nothing was written\\)"):
            RunDirGuard().on_run_start(config=compose(*TINY, *overrides))
    assert snapshot(finished) == before


def test_resume_runs_in_its_own_directory_and_a_missing_one_is_not_created(finished, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    config = compose(*TINY, "eval.episodes=60", f"resume={finished}")
    assert guard(config) == finished  # Hydra's record and log go with the run resumed, no dated directory
    missing = tmp_path / "missing"
    with pytest.raises(SystemExit, match=f"Cannot resume: no checkpoint.pt in {missing}"):
        RunDirGuard().on_run_start(config=compose(*TINY, f"resume={missing}"))
    with pytest.raises(FileNotFoundError, match="Cannot resume"):
        WBRMTrainer(tiny(), missing, progress=False, resume=True)
    assert list(tmp_path.iterdir()) == []  # neither missing/ nor outputs/


def test_config_error_creates_no_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit, match=r"ratio.bounds must hold two numbers"):
        RunDirGuard().on_run_start(config=compose(*TINY, "ratio.bounds=[0.5]"))
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------- overwrite=true
def test_overwrite_removes_every_output_of_the_earlier_run(finished, tmp_path):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(finished, run)
    old_csv = run / "logs" / "wbrm_lqr_exp1_seed0" / "scalars" / "q" / "loss.csv"
    old_csv.parent.mkdir(parents=True)
    old_csv.write_text("20,1.0\n")
    for name in ("training_curve.png", "evaluation.png", "wandb/offline-run/x.wandb", ".hydra/overrides.yaml",
                 "wbrm_offline.log"):
        (run / name).parent.mkdir(parents=True, exist_ok=True)
        (run / name).write_text("old")
    (run / "notes.txt").write_text("the user's own")
    config = compose(*TINY, f"hydra.run.dir={run}", "overwrite=true")
    assert guard(config) == run
    left = sorted(p.name for p in run.iterdir())
    assert left == ["notes.txt"], left  # Hydra's old record and log too: Hydra writes the new run's next
    results = WBRMTrainer(compose(*TINY, "overwrite=true", hydra=False), run, progress=False).run()
    assert results["status"] == "finished"


def test_overwrite_through_the_trainer_leaves_no_old_csv_rows(finished, tmp_path):
    import shutil

    from torchrl_wbrm.training.logging import make_logger

    run = tmp_path / "run"
    shutil.copytree(finished, run)
    cfg = tiny(overwrite=True, logger={"backend": "csv", "log_every": 5})
    for _ in range(2):  # the same seed twice: the second run's rows must not follow the first's
        trainer = WBRMTrainer(cfg, run, progress=False)
        trainer.logger = make_logger(cfg.logger, run, "wbrm_lqr_exp1_seed0")
        trainer.run()
    (csv,) = (run / "logs").rglob("loss_value.csv") or [None]
    steps = [line.split(",")[0] for line in csv.read_text().splitlines() if line.strip()]
    assert len(steps) == len(set(steps)), steps  # one row per step
