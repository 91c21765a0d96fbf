"""A run directory is data, and no command writes or deletes outside the folder it was given.

Each test is built as the hostile-but-fair probe did it:

- a run's record (``.hydra/overrides.yaml``) naming a YAML file in the run directory as ``env=``, ``algo=`` or
  ``logger=`` (whose ``hydra.callbacks`` entry would call ``os.makedirs`` outside it) is refused in one line, and
  nothing is created; other values the recipe does not offer are refused the same way;
- temporary files planted as symbolic links (``results.json.tmp``, ``history.json.tmp``, ``checkpoint.tmp``) are
  never written through, and a folder a run writes into that is a link is refused;
- the benchmark command validates its ids before touching anything: a ``--namespace`` leading out of ``--data-path``
  deletes and creates nothing;
- ``overwrite=true`` removes only what an earlier run wrote: not the user's own ``*.log``, not the command's own
  redirected output.
"""
from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

import pytest

from tests import inprocess
from tests.references import tiny_lqr_config
from torchrl_wbrm.configs import CONFIG_DIR
from torchrl_wbrm.training import WBRMTrainer
from torchrl_wbrm.training.resume import check_run_record, read_run_record

pytestmark = pytest.mark.usefixtures("single_thread")  # tests/conftest.py: one torch thread per test


def tiny(**overrides):
    return tiny_lqr_config({"checkpoint_every": 10}, **overrides)


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A finished tiny run: its directory (checkpoint, results, history)."""
    run_dir = tmp_path_factory.mktemp("finished")
    WBRMTrainer(tiny(), run_dir, progress=False).run()
    return run_dir


def digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


# ---------------------------------------------------------------------- case 1: the run's record
@pytest.mark.parametrize("group", ["env", "algo", "logger"])
def test_a_group_override_naming_a_yaml_in_the_run_dir_is_refused_and_runs_nothing(finished, tmp_path, group):
    """``<group>=<relative path to run/evil>``: Hydra would load ``run/evil.yaml`` by path, honour its
    ``# @package _global_`` and call its ``hydra.callbacks`` entry (``os.makedirs`` of a folder outside the run
    directory). The resume is refused in one line naming the record, and the folder is never created."""
    run = tmp_path / "run"
    shutil.copytree(finished, run)
    outside = tmp_path / "created_outside"
    (run / "evil.yaml").write_text(
        "# @package _global_\nhydra:\n  callbacks:\n    evil:\n      _target_: os.makedirs\n"
        f"      name: {outside}\n")
    relative = os.path.relpath(run / "evil", CONFIG_DIR / group)
    (run / ".hydra").mkdir()
    record = run / ".hydra" / "overrides.yaml"
    record.write_text(f"- {group}={relative}\n- q.steps=40\n")
    before = {p.name: digest(p) for p in run.iterdir() if p.is_file()}
    proc = inprocess.recipe(f"resume={run}", cwd=tmp_path, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode != 0
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert f"Cannot resume: {record} holds the override '{group}={relative}'" in lines[0]
    assert f"not one of the {group} group's options" in lines[0]
    assert not outside.exists()
    assert {p.name: digest(p) for p in run.iterdir() if p.is_file()} == before
    assert not (tmp_path / "outputs").exists()


@pytest.mark.parametrize("override, why", [
    ("env=lqr_exp9", "not one of the env group's options"),
    ("env=/etc/evil", "not one of the env group's options"),
    ("logger=../../x", "not one of the logger group's options"),
    ("algo=wbrm/../x", "not one of the algo group's options"),
    ("env@_global_=lqr_exp1", "another package"),
    ("env/sub=lqr_exp1", "not a setting of this recipe"),
    ("hydra.run.dir=/elsewhere", "not a setting of this recipe"),
    ("q.no_such_key=1", "not a setting of this recipe"),
    ("+q.step=1000", "not a setting of this recipe"),
    ("+q.lr=0.1", "adds or deletes a key"),
    ("~q.lr", "adds or deletes a key"),
    ("seed=1,2", "is a sweep"),
    ("q.lr=${oc.env:HOME}", "interpolation"),
])
def test_a_record_value_the_recipe_does_not_offer_is_refused(tmp_path, override, why):
    record = tmp_path / "overrides.yaml"
    with pytest.raises(ValueError, match="Cannot resume: .* holds the override") as err:
        check_run_record(record, ["q.lr=0.003", override])
    assert why in str(err.value) and "\n" not in str(err.value)


def test_a_record_of_the_recipes_own_settings_is_accepted(tmp_path):
    record = tmp_path / "overrides.yaml"
    record.write_text("- env=lqr_exp3\n- algo=td3bc\n- logger=none\n- q.lr=0.003\n- ++q.steps=40\n"
                      "- q.num_cells=[16,16]\n- env.lqr_data.dataset_dir=data/ds\n")
    assert read_run_record(record)[:2] == ["env=lqr_exp3", "algo=td3bc"]


@pytest.mark.parametrize("content, named", [
    (b"- q.lr=0.003\n- env=lqr_exp3\xe7\n", "is not UTF-8 text"),
    (b"- q.lr: [0.003\n", "is not valid YAML at line"),
    (b"q.lr: 0.003\n", "is not a list of overrides"),
])
def test_a_record_that_is_not_a_list_of_overrides_is_named_in_one_line(tmp_path, content, named):
    record = tmp_path / "overrides.yaml"
    record.write_bytes(content)
    with pytest.raises(ValueError) as err:
        read_run_record(record)
    assert str(err.value).startswith(f"Cannot resume: {record} {named}") and "\n" not in str(err.value)


# ---------------------------------------------------------------------- case 2: never through a link
def test_a_resume_never_writes_through_links_planted_as_temporaries(tmp_path):
    """``results.json.tmp``, ``history.json.tmp`` and ``checkpoint.tmp`` made links to files elsewhere: the resume
    of a run stopped at step 15 (so every file is written again) leaves the targets as they were, and the run's own
    files are regular files in the run directory."""
    run = tmp_path / "run"
    assert WBRMTrainer(tiny(), run, progress=False).run(until=15) is None
    targets = {}
    for name in ("results.json.tmp", "history.json.tmp", "checkpoint.tmp"):
        target = tmp_path / f"victim_{name}"
        target.write_text("the user's own\n")
        (run / name).symlink_to(target)
        targets[target] = digest(target)
    results = WBRMTrainer(tiny(), run, progress=False, resume=True).run()
    assert results["status"] == "finished" and results["final"]["step"] == 40
    assert {t: digest(t) for t in targets} == targets
    for name in ("results.json", "history.json", "checkpoint.pt"):
        assert (run / name).is_file() and not (run / name).is_symlink(), name
    assert not [p for p in run.iterdir() if p.name.endswith(".tmp")]


@pytest.mark.parametrize("linked", ["logs", "logs/run/scalars", ".hydra"])
def test_a_folder_the_run_writes_into_that_is_a_link_is_refused(finished, tmp_path, linked):
    run = tmp_path / "run"
    shutil.copytree(finished, run)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (run / linked).parent.mkdir(parents=True, exist_ok=True)
    (run / linked).symlink_to(elsewhere, target_is_directory=True)
    with pytest.raises(ValueError, match=f"^{run / linked} is a symbolic link \\(to {elsewhere}\\)"):
        WBRMTrainer(tiny(), run, progress=False, resume=True)
    assert list(elsewhere.iterdir()) == []


def test_a_file_created_fresh_replaces_a_link_and_leaves_its_target(tmp_path):
    from torchrl_wbrm.training.results import atomic_write

    target = tmp_path / "target"
    target.write_text("keep")
    (tmp_path / "out.json.tmp").symlink_to(target)
    (tmp_path / "out.json").symlink_to(target)
    atomic_write(tmp_path / "out.json", lambda f: f.write(b"new"))
    assert target.read_text() == "keep"
    assert not (tmp_path / "out.json").is_symlink() and (tmp_path / "out.json").read_text() == "new"


# ---------------------------------------------------------------------- case 3: the benchmark command
@pytest.mark.parametrize("overwrite", [True, False])
def test_the_benchmark_refuses_a_namespace_leading_out_of_its_data_path(tmp_path, capsys, overwrite):
    """``--namespace ../../victim``: refused in one line before anything is touched; the victim's folders outside
    ``--data-path`` are neither deleted nor created, and nothing is written under the data path."""
    from torchrl_wbrm.data.benchmark import main

    data = tmp_path / "a" / "b" / "D"
    data.mkdir(parents=True)
    victim = tmp_path / "a" / "victim" / "pendulum"
    for name in ("expert-v0", "behaviour-v0"):
        (victim / name).mkdir(parents=True)
        (victim / name / "mine.txt").write_text("the user's own")
    with pytest.raises(SystemExit) as exit_:
        main(["--data-path", str(data), "--tasks", "pendulum", "--namespace", "../../victim",
              *(["--overwrite"] if overwrite else [])])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "'../../victim/pendulum/expert-v0' is not a Minari dataset id" in err and "--namespace" in err
    assert sorted(p.name for p in victim.iterdir()) == ["behaviour-v0", "expert-v0"]
    assert all((victim / n / "mine.txt").read_text() == "the user's own" for n in ("expert-v0", "behaviour-v0"))
    assert list(data.iterdir()) == []
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["b", "victim"]


def test_the_benchmark_refuses_a_namespace_that_is_a_link_out_of_its_data_path(tmp_path, capsys):
    from torchrl_wbrm.data.benchmark import main

    data, outside = tmp_path / "D", tmp_path / "outside"
    data.mkdir()
    (outside / "pendulum" / "expert-v0").mkdir(parents=True)
    (data / "ns").symlink_to(outside, target_is_directory=True)
    with pytest.raises(SystemExit) as exit_:
        main(["--data-path", str(data), "--tasks", "pendulum", "--namespace", "ns", "--overwrite"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "outside the Minari data path" in err and len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in (outside / "pendulum").iterdir()) == ["expert-v0"]


# ---------------------------------------------------------------------- case 4: overwrite=true
def test_overwrite_keeps_the_users_logs_and_the_commands_own_output(finished, tmp_path, monkeypatch):
    """``overwrite=true`` removes the earlier run's outputs, its record and Hydra's job log, but not the user's
    ``analysis_notes.log``, not another redirected output (``second_run.log``), and not the job log's name when it
    is this command's own redirected stderr."""
    from tests.test_rundir import TINY, compose, guard

    run = tmp_path / "run"
    shutil.copytree(finished, run)
    (run / ".hydra").mkdir()
    (run / ".hydra" / "overrides.yaml").write_text("- q.lr=0.001\n")
    (run / "analysis_notes.log").write_text("the user's own notes")
    (run / "second_run.log").write_text("an earlier command's output")
    with open(run / "wbrm_offline.log", "w") as own:  # this command's stderr: `2> run/wbrm_offline.log`
        monkeypatch.setattr("sys.stderr", own)
        assert guard(compose(*TINY, f"hydra.run.dir={run}", "overwrite=true")) == run
    left = sorted(p.name for p in run.iterdir())
    assert left == ["analysis_notes.log", "second_run.log", "wbrm_offline.log"], left
    assert (run / "analysis_notes.log").read_text() == "the user's own notes"


def test_overwrite_removes_hydras_job_log_when_it_is_not_the_commands_output(finished, tmp_path):
    from tests.test_rundir import TINY, compose, guard

    run = tmp_path / "run"
    shutil.copytree(finished, run)
    (run / "wbrm_offline.log").write_text("Hydra's job log of the earlier run")
    (run / "notes.log").write_text("mine")
    guard(compose(*TINY, f"hydra.run.dir={run}", "overwrite=true"))
    assert sorted(p.name for p in run.iterdir()) == ["notes.log"]
