"""Nothing silent: what would give a wrong figure without a word is refused, or done whole.

- a resume after the data's rewards changed (past the first hundred rows) is refused: the checkpoint records the
  SHA-256 of every tensor of D, S^b and S^e;
- seeds the random generators would take as one (``seeds=[0, 4294967296]``: equal mod 2**32) are refused;
- ``overwrite=true`` with fewer seeds replaces the earlier multi-seed run whole: no stale ``seed2/`` is summarised;
- ``WBRMTrainer(WBRMConfig(seeds=[0, 1, 2]))`` is refused in one line pointing to ``run_seeds``;
- a key the schema does not have is refused however it is added (``+q.step=1000``, an attribute set on a dataclass).
"""
from __future__ import annotations

import json
import shutil

import pytest
import torch

from tests.references import tiny_lqr_config
from torchrl_wbrm.training import WBRMTrainer
from torchrl_wbrm.training.checkpoint import data_fingerprint
from torchrl_wbrm.training.config import WBRMConfig, merge_config, validate_config

pytestmark = pytest.mark.usefixtures("single_thread")  # tests/conftest.py: one torch thread per test


def tiny(**overrides):
    return tiny_lqr_config({"checkpoint_every": 10}, **overrides)


# ---------------------------------------------------------------------- case 5: the data fingerprint
def _save_with_rewards_scaled(datasets, path, row: int, factor: float) -> None:
    from torchrl_wbrm.data.datasets import OfflineDatasets

    d = datasets.transitions[:].clone()
    d["next", "reward"][row] *= factor
    changed = OfflineDatasets.from_tensordicts(d, datasets.behaviour_samples[:], datasets.expert_samples[:],
                                               metadata=dict(datasets.metadata))
    shutil.rmtree(path, ignore_errors=True)
    changed.save(path)


def test_a_resume_after_the_datas_rewards_changed_is_refused(tmp_path):
    """A saved dataset whose reward at row 300 (past the rows the old fingerprint summed) is doubled after the run
    stopped: the resume is refused in one line naming the checkpoint, before anything is written."""
    from torchrl_wbrm.tasks import get_task

    cfg = tiny(env={"lqr_data": {"dataset_dir": str(tmp_path / "ds")}})
    datasets = get_task(tiny().env).make_datasets(seed=0)
    _save_with_rewards_scaled(datasets, tmp_path / "ds", row=300, factor=1.0)
    run = tmp_path / "run"
    assert WBRMTrainer(cfg, run, progress=False).run(until=15) is None
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    _save_with_rewards_scaled(datasets, tmp_path / "ds", row=300, factor=2.0)
    with pytest.raises(ValueError) as err:
        WBRMTrainer(cfg, run, progress=False, resume=True)
    message = str(err.value)
    assert message.startswith(f"Cannot resume from {run / 'checkpoint.pt'}: its data differ") and "\n" not in message
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before
    # the same data again: the run resumes
    _save_with_rewards_scaled(datasets, tmp_path / "ds", row=300, factor=1.0)
    assert WBRMTrainer(cfg, run, progress=False, resume=True).run()["status"] == "finished"


def test_the_fingerprint_covers_every_tensor_of_every_set():
    from torchrl_wbrm.data.datasets import OfflineDatasets
    from torchrl_wbrm.tasks import get_task

    datasets = get_task(tiny().env).make_datasets(seed=0)
    base = data_fingerprint(datasets)
    sets = {"transitions": datasets.transitions[:], "behaviour_samples": datasets.behaviour_samples[:],
            "expert_samples": datasets.expert_samples[:]}
    for part, td in sets.items():
        for key in [k for k in td.keys(include_nested=True, leaves_only=True) if k != "index"]:  # the buffer's own
            changed = {name: t.clone() for name, t in sets.items()}
            value = changed[part].get(key)
            flat = value.reshape(-1)
            flat[-1] = flat[-1] + 1 if not value.dtype == torch.bool else ~flat[-1]
            other = OfflineDatasets.from_tensordicts(changed["transitions"], changed["behaviour_samples"],
                                                     changed["expert_samples"])
            assert data_fingerprint(other) != base, (part, key)


# ---------------------------------------------------------------------- case 6: seeds as the RNGs use them
@pytest.mark.parametrize("overrides, named", [
    ({"seeds": [0, 4294967296]}, "seeds holds 4294967296, out of range"),
    ({"seed": 2**32}, "seed=4294967296 is out of range"),
    ({"seed": 99999999999999999999}, "seed=99999999999999999999 is out of range"),
    ({"eval": {"seed": 2**40}}, "eval.seed=1099511627776 is out of range"),
])
def test_seeds_the_generators_would_take_as_one_are_refused(overrides, named):
    with pytest.raises(ValueError) as err:
        validate_config(tiny(**overrides))
    assert named in str(err.value) and "2**32 - 1" in str(err.value)


def test_the_largest_32_bit_seed_is_a_seed_of_its_own():
    validate_config(tiny(seeds=[0, 2**32 - 1]))


# ---------------------------------------------------------------------- case 7: overwrite=true, multi-seed
@pytest.mark.slow
def test_overwrite_with_fewer_seeds_replaces_the_multi_seed_run_whole(tmp_path):
    from torchrl_wbrm.training.reporting import load_results
    from torchrl_wbrm.training.seeds import run_seeds

    cfg = dict(algo="bc", q={"steps": 10, "eval_every": 10}, logger={"backend": "csv", "log_every": 5})
    run = tmp_path / "run"
    run_seeds(tiny(seeds=[0, 1, 2], **cfg), run, progress=False)
    assert (run / "seed2" / "results.json").is_file()
    (run / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="already holds a run"):
        run_seeds(tiny(seeds=[0, 1], **cfg), run, progress=False)
    run_seeds(tiny(seeds=[0, 1], overwrite=True, **cfg), run, progress=False)
    assert sorted(p.name for p in run.iterdir()) == ["notes.txt", "results.json", "seed0", "seed1"]
    assert sorted(r["seed"] for r in load_results(run)) == [0, 1]
    assert json.loads((run / "results.json").read_text())["seeds"] == [0, 1]


def test_the_recipe_guard_clears_every_seed_folder_on_overwrite(tmp_path):
    from tests.test_rundir import TINY, compose, guard

    run = tmp_path / "run"
    for seed in (0, 1, 2):
        (run / f"seed{seed}" / "logs").mkdir(parents=True)
        (run / f"seed{seed}" / "results.json").write_text("{}")
    (run / "seed2" / "mine.txt").write_text("the user's own")
    (run / "results.json").write_text("{}")
    guard(compose(*TINY, f"hydra.run.dir={run}", "seeds=[0,1]", "overwrite=true"))
    assert sorted(str(p.relative_to(run)) for p in run.rglob("*")) == ["seed2", "seed2/mine.txt"]


# ---------------------------------------------------------------------- case 8: the Python API and seeds=
def test_the_trainer_refuses_seeds_in_one_line_pointing_to_run_seeds(tmp_path):
    with pytest.raises(ValueError) as err:
        WBRMTrainer(WBRMConfig(seeds=[0, 1, 2]), tmp_path / "run", progress=False)
    message = str(err.value)
    assert message.startswith("seeds=[0, 1, 2]: a WBRMTrainer trains one run") and "run_seeds" in message
    assert "\n" not in message and not (tmp_path / "run").exists()


# ---------------------------------------------------------------------- case 10: unknown keys
@pytest.mark.parametrize("override, named", [
    ("+q.step=1000", "q.step is not a setting of this recipe (did you mean q.steps?)"),
    ("++eval.episode=3", "eval.episode is not a setting of this recipe (did you mean eval.episodes?)"),
    ("+unknown=1", "unknown is not a setting of this recipe"),
])
def test_an_added_key_the_schema_lacks_is_refused_at_start(tmp_path, monkeypatch, override, named):
    from tests.test_rundir import TINY, compose
    from torchrl_wbrm.training.hydra_guard import RunDirGuard

    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        RunDirGuard().on_run_start(config=compose(*TINY, override))
    assert str(exit_.value.code) == f"Refused (nothing was written): {named}; see " \
                                    f"torchrl_wbrm.training.config.WBRMConfig for every setting."
    assert list(tmp_path.iterdir()) == []


def test_an_attribute_set_on_a_config_dataclass_is_refused():
    cfg = WBRMConfig()
    cfg.q.step = 1000
    with pytest.raises(ValueError, match=r"^q.step is not a setting of this recipe \(did you mean q.steps\?\)"):
        merge_config(cfg)


@pytest.mark.slow
def test_the_recipe_refuses_a_resume_on_changed_data_in_one_line(tmp_path):
    """The same through the command: ``resume=X`` after the saved dataset's rewards changed is one line, no
    traceback, and the run's files are as they were."""
    import os

    from tests import inprocess
    from tests.test_clear_lines import TINY
    from torchrl_wbrm.tasks import get_task

    datasets = get_task(tiny().env).make_datasets(seed=0)
    _save_with_rewards_scaled(datasets, tmp_path / "ds", row=300, factor=1.0)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    overrides = [*TINY, f"env.lqr_data.dataset_dir={tmp_path / 'ds'}", f"hydra.run.dir={tmp_path / 'run'}"]
    assert inprocess.recipe(*overrides, cwd=tmp_path, env=env).returncode == 0
    before = {p.name: p.read_bytes() for p in (tmp_path / "run").iterdir() if p.is_file()}
    _save_with_rewards_scaled(datasets, tmp_path / "ds", row=300, factor=2.0)
    proc = inprocess.recipe(f"resume={tmp_path / 'run'}", "eval.episodes=60", cwd=tmp_path, env=env)
    assert proc.returncode == 1
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert lines[0].startswith(f"Refused: Cannot resume from {tmp_path / 'run' / 'checkpoint.pt'}: its data differ")
    assert {p.name: p.read_bytes() for p in (tmp_path / "run").iterdir() if p.is_file()} == before


def test_summarise_never_averages_a_stale_seed_folder_into_a_multi_seed_run(tmp_path):
    """A ``seed2/`` beside a multi-seed run's record that does not list it (left by an earlier run) is not one of
    its runs: ``load_results`` (what ``recipes/summarise.py`` reads) counts the record's seeds only."""
    from torchrl_wbrm.training.reporting import load_results

    run = tmp_path / "run"
    for seed in (0, 1, 2):
        (run / f"seed{seed}").mkdir(parents=True)
        (run / f"seed{seed}" / "results.json").write_text(json.dumps({"seed": seed, "final": {"return": seed}}))
    runs = [{"seed": s, "status": "finished", "final": {"return": s}} for s in (0, 1)]
    (run / "results.json").write_text(json.dumps({"kind": "seeds", "seeds": [0, 1], "runs": runs}))
    assert sorted(r["seed"] for r in load_results(run)) == [0, 1]
