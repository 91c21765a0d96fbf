"""Resuming a run, and what refuses or stops one: run directories, resume, signals, divergence, plots, summaries,
config.

Each failure case asserts the error type and that the message names the key, file or setting; the run-directory
and resume tests check that nothing on disk changed.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import signal
import sys
from pathlib import Path

import pytest
import torch

from tests.references import tiny_lqr_config
from torchrl_wbrm.training import WBRMTrainer
from torchrl_wbrm.algos import ALGOS
from torchrl_wbrm.training.config import WBRMConfig, validate_config
from torchrl_wbrm.training.resume import CONTINUABLE_KEYS
from torchrl_wbrm.training.stops import RunInterrupted
from torchrl_wbrm.training.plots import LOSS_TITLES

ROOT = Path(__file__).resolve().parents[1]


pytestmark = pytest.mark.usefixtures("single_thread")  # tests/conftest.py: one torch thread per test


def tiny(**overrides) -> WBRMConfig:
    """The tiny LQR run (tests/references.py), with this file's own settings."""
    return tiny_lqr_config({"q": {"lr_schedule": "constant"},  # a budget can grow only under a constant rate (see the cosine test)
        "eval": {"q_samples": 400}, "checkpoint_every": 10}, **overrides)


def snapshot(root: Path) -> dict[str, tuple[int, str, int]]:
    return {
        str(p.relative_to(root)): (p.stat().st_size, hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
        for p in sorted(Path(root).rglob("*")) if p.is_file()
    }


def strict_json(path: Path):
    def refuse(name):
        raise ValueError(f"{path} holds {name}, which is not JSON")

    return json.loads(path.read_text(), parse_constant=refuse)


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A finished tiny run (40 steps): its directory."""
    run_dir = tmp_path_factory.mktemp("finished")
    WBRMTrainer(tiny(), run_dir, progress=False).run()
    return run_dir


# ---------------------------------------------------------------------- run directories
def test_new_run_refuses_a_run_directory(finished, tmp_path):
    before = snapshot(finished)
    with pytest.raises(FileExistsError, match=rf"{finished} already holds a run \(checkpoint.pt, results.json.*overwrite=true"):
        WBRMTrainer(tiny(), finished, progress=False)
    assert snapshot(finished) == before
    # overwrite=true replaces it: the old files are removed before the new run writes its own
    other = tmp_path / "run"
    other.mkdir()
    (other / "results.json").write_text("{}")
    trainer = WBRMTrainer(tiny(overwrite=True, q={"steps": 20}), other, progress=False)
    assert not (other / "results.json").exists()
    assert trainer.run()["config"]["q"]["steps"] == 20


# ---------------------------------------------------------------------- resume
@pytest.mark.parametrize(
    "overrides, named",
    [
        ({"q": {"lr": 1e-5}}, ["q.lr: 0.001 -> 1e-05"]),
        ({"q": {"residual": "absolute_mean", "gamma": 0.5}}, ["q.gamma: 0.9 -> 0.5", "q.residual: 'squared' -> 'absolute_mean'"]),
        ({"ratio": {"alpha": 1.0}, "algo": "brm"}, ["algo: 'wbrm' -> 'brm'", "ratio.alpha: 0.5 -> 1.0"]),
    ],
)
def test_resume_refuses_changed_settings(finished, overrides, named):
    before = snapshot(finished)
    with pytest.raises(ValueError, match="cannot change in a resumed run") as err:
        WBRMTrainer(tiny(**overrides), finished, progress=False, resume=True)
    for text in named:
        assert text in str(err.value)
    assert snapshot(finished) == before


def test_a_setting_added_after_a_run_was_saved_is_no_change_at_its_default():
    """A saved config without a setting that exists now (the run was saved before it was added) matches a config
    holding that setting at its default: resuming it and reusing its results are allowed. The same setting at another
    value is a change, refused and named."""
    from torchrl_wbrm.training.config import config_as_dict
    from torchrl_wbrm.training.resume import changed_keys, check_finished_config

    now = config_as_dict(tiny())
    saved = json.loads(json.dumps(now))
    del saved["ratio"]["aggregate"]  # settings added after the run was saved
    del saved["baselines"]["bc"]
    assert changed_keys(saved, now) == {}
    check_finished_config(Path("results.json"), saved, now)
    other = json.loads(json.dumps(now))
    other["ratio"]["aggregate"] = "episode"
    assert changed_keys(saved, other) == {"ratio.aggregate": (None, "episode")}
    with pytest.raises(ValueError, match="ratio.aggregate: None -> 'episode'"):
        check_finished_config(Path("results.json"), saved, other)
    assert changed_keys(now, saved)  # a setting the new config lacks is still a change


def test_resume_refuses_a_smaller_budget(finished):
    before = snapshot(finished)
    with pytest.raises(ValueError, match="q.steps=20 is smaller than the 40 steps already trained"):
        WBRMTrainer(tiny(q={"steps": 20}), finished, progress=False, resume=True)
    assert snapshot(finished) == before


def test_resume_accepts_continuable_keys_and_reevaluates(finished, tmp_path):
    import shutil

    assert "q.steps" in CONTINUABLE_KEYS
    run = tmp_path / "copy"
    shutil.copytree(finished, run)
    old = strict_json(run / "results.json")["final"]
    # other evaluation settings on a finished run: evaluated anew, not relabelled
    results = WBRMTrainer(tiny(eval={"episodes": 80, "train_episodes": 20, "q_samples": 400}), run, progress=False,
                          resume=True).run()
    assert results["config"]["eval"]["episodes"] == 80
    assert results["final"]["return"] != old["return"] and results["final"]["step"] == 40
    # a larger budget continues training
    results = WBRMTrainer(tiny(q={"steps": 60}), run, progress=False, resume=True).run()
    assert results["final"]["step"] == 60


def test_resume_refuses_a_new_budget_under_a_cosine_schedule(tmp_path):
    """The cosine schedule's horizon is q.steps (and torch's cosine rises again past it): a run on that schedule
    cannot be extended, only restarted."""
    WBRMTrainer(tiny(q={"steps": 20, "eval_every": 20, "lr_schedule": "cosine"}), tmp_path, progress=False).run()
    before = snapshot(tmp_path)
    with pytest.raises(ValueError, match=r"q.steps: 20 -> 40.*not with an lr schedule"):
        WBRMTrainer(tiny(q={"steps": 40, "eval_every": 20, "lr_schedule": "cosine"}), tmp_path, progress=False, resume=True)
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("damage", ["truncate", "garbage", "not_a_checkpoint"])
def test_corrupted_checkpoint_names_the_file(finished, tmp_path, damage):
    import shutil

    run = tmp_path / "copy"
    shutil.copytree(finished, run)
    ckpt = run / "checkpoint.pt"
    if damage == "truncate":
        os.truncate(ckpt, ckpt.stat().st_size // 2)
    elif damage == "garbage":
        ckpt.write_bytes(b"\x00garbage" * 100)
    else:
        torch.save({"step": 3}, ckpt)
    before = snapshot(run)
    with pytest.raises(RuntimeError, match=rf"Cannot resume: {ckpt} (is corrupted|is not a complete checkpoint)"):
        WBRMTrainer(tiny(), run, progress=False, resume=True)
    assert snapshot(run) == before


def test_sigterm_writes_a_checkpoint_and_says_how_to_resume(tmp_path):
    # what was installed before the run (SIG_DFL, or a handler an earlier test's torchrl memmap storage left)
    before = signal.getsignal(signal.SIGTERM)
    trainer = WBRMTrainer(tiny(), tmp_path, progress=False)
    step = trainer._q_step

    def signalled(i):
        if i == 15:
            os.kill(os.getpid(), signal.SIGTERM)
        return step(i)

    trainer._q_step = signalled
    with pytest.raises(RunInterrupted, match=rf"SIGTERM received: stopped in stage 'q' at step 15.*resume={tmp_path}") as err:
        trainer.run()
    assert err.value.exit_code == 128 + signal.SIGTERM
    assert signal.getsignal(signal.SIGTERM) == before  # the run's handler is removed again, the previous one back
    assert not (tmp_path / "results.json").exists()
    resumed = WBRMTrainer(tiny(), tmp_path, progress=False, resume=True)
    assert resumed.state == {"stage": "q", "step": 15}
    assert resumed.run()["status"] == "finished"


# ---------------------------------------------------------------------- divergence
def test_non_finite_loss_stops_the_run_and_keeps_the_last_finite_checkpoint(tmp_path):
    results = WBRMTrainer(tiny(q={"lr": 1e10}), tmp_path, progress=False).run()
    assert results["status"] == "diverged"
    d = results["diverged"]
    assert d["stage"] == "q" and d["step"] >= 1 and d["figure"].startswith("loss") and "stage 'q' at step" in d["message"]
    saved = strict_json(tmp_path / "results.json")  # valid JSON: no bare NaN
    assert saved["status"] == "diverged" and saved["diverged"]["figure"] == d["figure"]
    strict_json(tmp_path / "history.json")
    ckpt = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    assert ckpt["state"]["step"] == d["checkpoint_step"] < d["step"]
    assert all(torch.isfinite(v).all() for v in ckpt["q_loss"].values() if v.is_floating_point())


def test_non_finite_ratio_stops_the_run_in_stage_1(tmp_path):
    results = WBRMTrainer(tiny(ratio={"lr": 1e30, "grad_clip": None}), tmp_path, progress=False).run()
    assert results["status"] == "diverged"
    assert results["diverged"]["stage"] == "ratio" and "density_ratio" in results["diverged"]["figure"]
    assert strict_json(tmp_path / "results.json")["diverged"]["step"] == results["diverged"]["step"]


def test_run_with_a_damaged_cache_entry_trains_on_rebuilt_data(tmp_path):
    cache = tmp_path / "cache"
    first = WBRMTrainer(tiny(data_cache=str(cache)), tmp_path / "r1", progress=False)
    (entry,) = [p for p in cache.iterdir() if not p.name.startswith(".")]
    os.truncate(entry / "transitions" / "observation.memmap", 0)
    os.truncate(entry / "transitions" / "next" / "reward.memmap", 1000)
    with pytest.warns(UserWarning, match=r"failed verification and is rebuilt"):
        second = WBRMTrainer(tiny(data_cache=str(cache)), tmp_path / "r2", progress=False)
    for key in ("observation", ("next", "reward")):
        assert torch.equal(second.q_train_data[key], first.q_train_data[key])
    assert (second.q_train_data["observation"] != 0).all()


def test_recipe_exits_non_zero_on_divergence(tmp_path, monkeypatch, capsys):
    import runpy

    monkeypatch.setattr(sys, "argv", [
        "wbrm_offline.py", "ratio.steps=10", "q.steps=20", "q.lr=1e10", "eval.episodes=50", "eval.train_episodes=20",
        "eval.q_samples=400", "logger=none", "env.lqr_data.behaviour_episodes=40", "env.lqr_data.expert_episodes=20",
        "env.lqr_data.parallel_envs=20", f"hydra.run.dir={tmp_path}", "hydra/job_logging=none", "hydra/hydra_logging=none",
    ])
    with pytest.raises(SystemExit) as exit_:
        runpy.run_path(str(ROOT / "recipes" / "wbrm_offline.py"), run_name="__main__")
    captured = capsys.readouterr()
    assert exit_.value.code == 2
    assert "Training diverged in stage 'q' at step" in captured.err and "return nan" not in captured.out
    assert strict_json(tmp_path / "results.json")["status"] == "diverged"


def test_finite_blow_up_is_flagged(tmp_path):
    results = WBRMTrainer(tiny(q={"lr": 100.0}), tmp_path, progress=False).run()
    scale = results["q_scale"]
    assert results["status"] == "finished" and "q_blow_up" in results["flags"]
    assert scale["blow_up"] and scale["max_abs_q_mean"] > scale["factor"] * scale["bound"]
    from torchrl_wbrm.training.reporting import summarise

    assert "FLAG q_blow_up" in summarise(results)


def test_summarise_excludes_unfinished_runs(tmp_path, finished, monkeypatch, capsys):
    import shutil

    for name in ("a", "b"):
        shutil.copytree(finished, tmp_path / name)
    diverged = strict_json(tmp_path / "b" / "results.json")
    diverged.update(status="diverged", diverged={"stage": "q", "step": 3, "figure": "loss_value", "value": "nan"})
    diverged["final"]["regret"] = None
    (tmp_path / "b" / "results.json").write_text(json.dumps(diverged))
    unflagged = strict_json(tmp_path / "a" / "results.json")
    unflagged["flags"] = []  # the tiny run's own flags (below_behaviour) aside: a is the unflagged run
    (tmp_path / "a" / "results.json").write_text(json.dumps(unflagged))
    flagged = strict_json(tmp_path / "a" / "results.json")
    shutil.copytree(finished, tmp_path / "c")
    flagged.update(flags=["q_blow_up"], q_scale={"figure": "q_mean_expert", "max_abs_q_mean": 1e6, "factor": 10, "bound": 100})
    (tmp_path / "c" / "results.json").write_text(json.dumps(flagged))
    import runpy

    monkeypatch.setattr(sys, "argv", ["summarise.py", str(tmp_path)])
    runpy.run_path(str(ROOT / "recipes" / "summarise.py"), run_name="__main__")
    out = capsys.readouterr().out
    assert "3 runs under" in out and "2 finished, 1 not finished (excluded)" in out
    assert "excluded (diverged):" in out and "b/results.json" in out and "step 3 loss_value" in out
    assert "flagged q_blow_up:" in out and "c/results.json" in out
    row = [line for line in out.splitlines() if line.startswith("| lqr_exp1")]
    assert len(row) == 1 and "| 2 | 1 |" in row[0]  # two seeds' runs, one flagged; the diverged one left out
    from torchrl_wbrm.training.reporting import load_results, results_table

    table = results_table(load_results(tmp_path), ["env.name"], {"regret": "final.regret"})
    assert "| lqr_exp1 | 2 | 1 |" in table and "1 run(s) excluded from the table (1 diverged)" in table


def test_summarise_minari_runs_seed_by_seed(tmp_path, monkeypatch, capsys):
    """Minari runs get the normalised score, ``--per-seed`` lists it with the step delivered and the flags, and a
    flag other than ``q_blow_up`` is named without the blow-up's inequality (which it does not hold)."""
    def run(seed, score, flags, step):
        final = {"normalised_score": score, "return": 10.0 * score, "selected_step": step}
        return {"seed": seed, "status": "finished", "config": {"algo": "brm", "q": {"steps": 800}}, "final": final,
                "flags": flags, "q_scale": {"figure": "q_mean", "max_abs_q_mean": 5.0, "factor": 10, "bound": 50.0,
                                            "blow_up": False}}
    for seed, score, flags, step in ((1, 60.0, ["return_fell"], 400), (0, 80.0, [], 800)):
        (tmp_path / f"seed{seed}").mkdir()
        (tmp_path / f"seed{seed}" / "results.json").write_text(json.dumps(run(seed, score, flags, step)))
    import runpy

    monkeypatch.setattr(sys, "argv", ["summarise.py", str(tmp_path), "--group-by", "algo", "--digits", "1",
                                      "--per-seed", "normalised score"])
    runpy.run_path(str(ROOT / "recipes" / "summarise.py"), run_name="__main__")
    out = capsys.readouterr().out
    assert "flagged return_fell:" in out and "r_max/(1 - gamma)" not in out
    row = [line for line in out.splitlines() if line.startswith("| brm")]
    assert row == ["| brm | 2 | 1 | 70.0 ± 127.1 | 700.0 ± 1270.6 | 0: 80.0 @800, 1: 60.0 @400 (return_fell) |"]
    monkeypatch.setattr(sys, "argv", ["summarise.py", str(tmp_path), "--per-seed", "regret"])
    with pytest.raises(SystemExit) as exit_:
        runpy.run_path(str(ROOT / "recipes" / "summarise.py"), run_name="__main__")
    assert exit_.value.code == 2 and "--per-seed 'regret'" in capsys.readouterr().err


# ---------------------------------------------------------------------- every algo has a plot title
def test_every_algo_has_a_plot_title():
    assert set(LOSS_TITLES) == set(ALGOS)

# every algo's run with plots on, through the recipe: tests/test_baselines.py
# (test_each_algo_writes_results_and_figures_through_the_recipe)


# ---------------------------------------------------------------------- config, before any data
@pytest.mark.parametrize(
    "overrides, named",
    [
        ({"seed": -1}, "seed must be >= 0, got -1"),
        ({"eval": {"q_samples": 0}}, "eval.q_samples must be >= 2"),
        ({"env": {"lqr_data": {"parallel_envs": 0}}}, "env.lqr_data.parallel_envs must be >= 1, got 0"),
        ({"threads": -1}, "threads must be >= 1 or null"),
        ({"q": {"lr": math.inf}}, "q.lr=inf: every number in the config must be finite"),
        ({"device": "tpu"}, "device='tpu'"),
        ({"env": {"lqr": {"reward_clip": 1.0}}}, "env.lqr.reward_clip=1.0"),
    ],
)
def test_config_errors_name_the_key_before_any_data(tmp_path, overrides, named):
    cfg = tiny(data_cache=str(tmp_path / "cache"), **overrides)
    with pytest.raises(ValueError) as err:
        WBRMTrainer(cfg, tmp_path / "run", progress=False)
    assert named in str(err.value)
    assert not (tmp_path / "cache").exists()  # refused before any data were collected


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message on a machine without CUDA")
def test_cuda_without_cuda_names_device(tmp_path):
    with pytest.raises(ValueError, match=r"device='cuda' but CUDA is not available"):
        validate_config(tiny(device="cuda"))
    with pytest.raises(ValueError, match=r"device='cuda:0' but CUDA is not available.*use device=cpu"):
        WBRMTrainer(tiny(device="cuda:0", data_cache=str(tmp_path / "cache")), tmp_path / "run", progress=False)
    assert not (tmp_path / "cache").exists()


def test_three_dimensional_lqr_is_refused_with_the_clip_and_runs_without(tmp_path):
    three = {"F": [[0.5, 0, 0], [0, 0.5, 0], [0, 0, 0.5]], "G": [[0.5, 0], [0, 0.5], [0.2, 0.2]],
             "S": [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]}
    with pytest.raises(ValueError, match=r"env.lqr: a 3-dimensional state with the reward clipped.*env.lqr.reward_clip=null"):
        validate_config(tiny(env={"name": "lqr_custom", "lqr": three}))
    cfg = tiny(env={"name": "lqr_custom", "lqr": {**three, "reward_clip": None}}, q={"steps": 10, "eval_every": 10})
    results = WBRMTrainer(cfg, tmp_path, progress=False).run()
    assert results["status"] == "finished" and math.isfinite(results["final"]["regret"])
