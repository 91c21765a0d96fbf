"""The hostile-but-fair user's probes of the recipe, replayed as real commands at a tiny budget: two runs into one
directory, dated directories of one second, a saved dataset behind the data cache, a collapsed stage 1, Ctrl-C during
the final evaluation, ``overwrite=true`` and old logs (and the user's own), refused commands that must change nothing
on disk, config errors that must name their key, resumes that must leave no stray directory, a run record naming a
YAML file in the run directory, temporary files planted as links, and a benchmark namespace leading out of its data
path.

    python tools/reliability_probes.py                  # every probe (about 8 minutes on 2 cores)
    python tools/reliability_probes.py --fast           # the ones that take a few seconds each
    python tools/reliability_probes.py --only sigint_during_final_evaluation
    python tools/reliability_probes.py --list

Each probe runs ``python recipes/wbrm_offline.py`` (and ``recipes/make_dataset.py``) in subprocesses in a fresh
temporary folder and checks exit codes, messages and files; one line per probe, ``PASS`` or ``FAIL`` with what was
seen, and the exit status is the number of failures. The same cases run in CI, faster and in process, as
``tests/test_rundir.py`` and ``tests/test_trainer_stops.py``; this script is the end-to-end check of
the commands themselves (signals, concurrent processes, Hydra's own files).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RECIPE = [sys.executable, str(ROOT / "recipes" / "wbrm_offline.py")]
MAKE_DATASET = [sys.executable, str(ROOT / "recipes" / "make_dataset.py")]
#: the budget of every probe: tiny data, networks and evaluations
B = ["ratio.steps=20", "q.steps=40", "q.eval_every=20", "eval.episodes=50", "eval.train_episodes=20", "logger=none",
     "plots=false", "env.lqr_data.behaviour_episodes=40", "env.lqr_data.expert_episodes=20",
     "env.lqr_data.parallel_envs=20", "q.num_cells=[16,16]", "q.actor_num_cells=[16,16]", "eval.q_samples=300",
     "ratio.num_cells=[16,16]"]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg", "WANDB_MODE": "offline"}


class ProbeFailed(AssertionError):
    pass


def check(condition: bool, what: str) -> None:
    if not condition:
        raise ProbeFailed(what)


def run(cmd: list[str], cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, cwd=cwd, env=ENV, capture_output=True, text=True, timeout=timeout)


def start(cmd: list[str], cwd: Path) -> subprocess.Popen:
    return subprocess.Popen(cmd, cwd=cwd, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def snapshot(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def results(run_dir: Path) -> dict:
    return json.loads((run_dir / "results.json").read_text())


def last_line(text: str) -> str:
    lines = text.strip().splitlines()
    return lines[-1] if lines else ""


# ---------------------------------------------------------------------- the probes
def two_runs_into_one_directory(tmp: Path) -> str:
    procs = {lr: start([*RECIPE, *B, f"q.lr={lr}", "hydra.run.dir=X"], tmp) for lr in (0.001, 0.003)}
    outcome = {lr: (p.wait(timeout=300), p.stderr.read()) for lr, p in procs.items()}
    codes = sorted(code for code, _ in outcome.values())
    check(codes == [0, 1], f"exit codes {codes}, expected one 0 and one 1")
    winner = next(lr for lr, (code, _) in outcome.items() if code == 0)
    loser_err = next(err for code, err in outcome.values() if code == 1)
    check("in use by another run" in loser_err or "already holds a run" in loser_err,
          f"the refused run says: {last_line(loser_err)!r}")
    check(results(tmp / "X")["config"]["q"]["lr"] == winner, "results.json is not the finished run's")
    return f"q.lr={winner} finished; the other: {last_line(loser_err)[:70]}..."


def dated_directories_of_one_second(tmp: Path) -> str:
    procs = [start([*RECIPE, *B, f"q.lr={lr}"], tmp) for lr in (0.001, 0.003)]
    codes = [p.wait(timeout=300) for p in procs]
    check(codes == [0, 0], f"exit codes {codes}")
    dirs = sorted(p.parent for p in (tmp / "outputs").rglob("results.json"))
    check(len(dirs) == 2, f"{len(dirs)} run directories with results, expected 2")
    lrs = sorted(results(d)["config"]["q"]["lr"] for d in dirs)
    check(lrs == [0.001, 0.003], f"the runs' q.lr: {lrs}")
    return ", ".join(d.name for d in dirs)


def saved_dataset_behind_the_data_cache(tmp: Path) -> str:
    small = ["env.lqr_data.behaviour_episodes=40", "env.lqr_data.expert_episodes=20", "env.lqr_data.parallel_envs=20"]
    use = [*B, "env.lqr_data.dataset_dir=ds", "data_cache=cache"]
    check(run([*MAKE_DATASET, *small, "out=ds"], tmp).returncode == 0, "make_dataset failed")
    first = run([*RECIPE, *use, "hydra.run.dir=r1"], tmp)
    check(first.returncode == 0, f"first run: {last_line(first.stderr)}")
    check(run([*MAKE_DATASET, *small, "seed=1", "out=ds", "overwrite=true"], tmp).returncode == 0,
          "make_dataset seed=1 failed")
    second = run([*RECIPE, *use, "hydra.run.dir=r2"], tmp)
    check(second.returncode == 0, f"second run: {last_line(second.stderr)}")
    check("rebuilt" not in first.stderr + second.stderr, "a cache rebuild warning")
    a, b = (results(tmp / r)["data"].get("behaviour_mean_return") for r in ("r1", "r2"))
    check(a != b, f"both runs trained on the same data (behaviour mean return {a})")
    cached = [p for p in (tmp / "cache").rglob("*") if p.is_file()] if (tmp / "cache").exists() else []
    check(not cached, f"{len(cached)} cached files of data already on disk")
    return f"behaviour mean return {a:.4f} then {b:.4f}; nothing cached"


def collapsed_stage_1(tmp: Path) -> str:
    proc = run([*RECIPE, *B, "ratio.lr=1.0", "ratio.steps=300", "hydra.run.dir=X"], tmp)
    check(proc.returncode == 0, f"exit {proc.returncode}: {last_line(proc.stderr)}")
    flags = results(tmp / "X")["flags"]
    check("ratio_collapse" in flags, f"flags {flags}")
    check("FLAG ratio_collapse" in proc.stdout, "no FLAG line in the summary")
    return f"flags {flags}"


def sigint_during_final_evaluation(tmp: Path) -> str:
    # a final evaluation of 2 million episodes (several seconds), the first interrupt arriving inside it
    cmd = [*RECIPE, *B, "q.steps=20", "q.eval_every=20", "eval.episodes=2000000", "checkpoint_every=0",
           "hydra.run.dir=X"]
    proc = start(cmd, tmp)
    deadline = time.time() + 120
    while not (tmp / "X" / "checkpoint.pt").exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.1)
    time.sleep(3.0)  # 20 tiny Q steps, then the final evaluation
    sent = time.perf_counter()
    proc.send_signal(signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise ProbeFailed("still running 20 s after Ctrl-C")
    stopped = time.perf_counter() - sent
    check(proc.returncode == 130, f"exit {proc.returncode}: {last_line(err)}")
    check("during the evaluation" in err and "resume=" in err, f"says {last_line(err)!r}")
    resumed = run([*RECIPE, "resume=X"], tmp, timeout=600)
    check(resumed.returncode == 0, f"resume: {last_line(resumed.stderr)}")
    return f"stopped {stopped:.1f} s after Ctrl-C; resume=X finished"


def overwrite_leaves_no_old_logs(tmp: Path) -> str:
    for extra in ([], ["overwrite=true"]):
        proc = run([*RECIPE, *B, "logger=csv", "hydra.run.dir=X", *extra], tmp)
        check(proc.returncode == 0, f"exit {proc.returncode}: {last_line(proc.stderr)}")
    csvs = list((tmp / "X" / "logs").rglob("*.csv"))
    check(bool(csvs), "no CSV logs")
    for csv in csvs:
        steps = [line.split(",")[0] for line in csv.read_text().splitlines() if line.strip()]
        check(len(steps) == len(set(steps)), f"{csv.name} has two rows for one step")
    return f"{len(csvs)} CSV files, one row per step"


def refused_commands_change_nothing(tmp: Path) -> str:
    check(run([*RECIPE, *B, "hydra.run.dir=X"], tmp).returncode == 0, "the first run failed")
    before = snapshot(tmp)
    said = []
    for cmd in ([*RECIPE, *B, "hydra.run.dir=X"],  # a new run into a run directory
                [*RECIPE, *B, "q.lr=0.003", "resume=X"],  # a resume with a changed setting
                [*RECIPE, *B, "q.lr=0.003", "resume=X", "hydra.run.dir=X"],
                [*RECIPE, "resume=missing"]):  # a resume of a directory that does not exist
        proc = run(cmd, tmp)
        check(proc.returncode != 0, f"accepted: {' '.join(cmd[2:])}")
        said.append(last_line(proc.stderr)[:60])
    after = snapshot(tmp)
    changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
    check(not changed, f"files changed: {changed[:5]}")
    check(not (tmp / "missing").exists() and not (tmp / "outputs").exists(), "a directory was created")
    proc = run([*RECIPE, "resume=X", "eval.episodes=60"], tmp)
    check(proc.returncode == 0, f"an accepted resume failed: {last_line(proc.stderr)}")
    check(not (tmp / "outputs").exists(), "the resume left a dated directory under outputs/")
    return "4 refusals, nothing changed; resume=X wrote no outputs/"


def config_errors_name_the_key(tmp: Path) -> str:
    cases = {"ratio.bounds=[0.5]": "ratio.bounds",
             "env.lqr_data.behaviour_episodes=2": "env.lqr_data.behaviour_episodes must be >= 4",
             "logger.project=team/project": "logger.project"}
    for override, named in cases.items():
        extra = ["logger=wandb"] if override.startswith("logger.") else []
        proc = run([*RECIPE, *B, *extra, override], tmp)
        check(proc.returncode != 0 and named in proc.stderr, f"{override}: {last_line(proc.stderr)!r}")
    check(not any(tmp.iterdir()), "a refused config wrote files")
    return f"{len(cases)} errors named their key, nothing written"


def a_run_record_naming_a_yaml_runs_nothing(tmp: Path) -> str:
    check(run([*RECIPE, *B, "hydra.run.dir=X"], tmp).returncode == 0, "the first run failed")
    outside = tmp / "created_outside"
    (tmp / "X" / "evil.yaml").write_text("# @package _global_\nhydra:\n  callbacks:\n    evil:\n"
                                         f"      _target_: os.makedirs\n      name: {outside}\n")
    record = tmp / "X" / ".hydra" / "overrides.yaml"
    saved = record.read_text()
    said = []
    for group in ("env", "algo", "logger"):
        relative = os.path.relpath(tmp / "X" / "evil", ROOT / "configs" / group)
        record.write_text(saved + f"- {group}={relative}\n")
        before = snapshot(tmp / "X")
        proc = run([*RECIPE, "resume=X"], tmp)
        check(proc.returncode != 0, f"{group}=<path>: the resume ran")
        lines = [line for line in proc.stderr.splitlines() if line.strip()]
        check(len(lines) == 1 and "Traceback" not in proc.stderr, f"{group}=<path>: {len(lines)} lines")
        check(not outside.exists(), f"{group}=<path>: a folder outside the run directory was created")
        check(snapshot(tmp / "X") == before, f"{group}=<path>: the run directory changed")
        said.append(lines[0])
    return f"3 group overrides refused: {said[0][:70]}..."


def planted_links_are_not_written_through(tmp: Path) -> str:
    check(run([*RECIPE, *B, "q.steps=400", "q.eval_every=400", "checkpoint_every=40", "hydra.run.dir=X"], tmp)
          .returncode == 0, "the first run failed")
    victims = {}
    for name in ("results.json.tmp", "history.json.tmp", "checkpoint.tmp"):
        victim = tmp / f"victim_{name}"
        victim.write_text("mine\n")
        (tmp / "X" / name).symlink_to(victim)
        victims[victim] = victim.read_text()
    proc = run([*RECIPE, "resume=X", "eval.episodes=60"], tmp)
    check(proc.returncode == 0, f"resume: {last_line(proc.stderr)}")
    check(all(v.read_text() == text for v, text in victims.items()), "a file outside the run directory changed")
    check(not any((tmp / "X" / n).is_symlink() for n in ("results.json", "history.json", "checkpoint.pt")),
          "a run file is a link")
    return "3 links planted as temporaries: their targets untouched, the run's files regular"


def benchmark_namespace_out_of_its_data_path(tmp: Path) -> str:
    victim = tmp / "victim" / "pendulum" / "expert-v0"
    victim.mkdir(parents=True)
    (victim / "mine.txt").write_text("mine")
    (tmp / "a" / "D").mkdir(parents=True)
    proc = run([sys.executable, "-m", "torchrl_wbrm.data.benchmark", "--data-path", "a/D", "--tasks", "pendulum",
                "--namespace", "../../victim", "--overwrite"], tmp)
    check(proc.returncode == 2, f"exit {proc.returncode}: {last_line(proc.stderr)}")
    check("Traceback" not in proc.stderr, "a traceback")
    check((victim / "mine.txt").is_file(), "the victim's folder was deleted")
    check(not any((tmp / "a" / "D").iterdir()), "something was written under the data path")
    return last_line(proc.stderr)[:90]


def overwrite_keeps_the_users_logs(tmp: Path) -> str:
    check(run([*RECIPE, *B, "hydra.run.dir=X"], tmp).returncode == 0, "the first run failed")
    (tmp / "X" / "analysis_notes.log").write_text("mine")
    with open(tmp / "X" / "second_run.log", "w") as out:
        proc = subprocess.run([*RECIPE, *B, "hydra.run.dir=X", "overwrite=true"], cwd=tmp, env=ENV, stdout=out,
                              stderr=subprocess.STDOUT, text=True, timeout=300)
    check(proc.returncode == 0, f"exit {proc.returncode}")
    check((tmp / "X" / "analysis_notes.log").read_text() == "mine", "the user's log was removed")
    check("run directory:" in (tmp / "X" / "second_run.log").read_text(), "the command's own output was lost")
    return "analysis_notes.log and the redirected output kept"


PROBES = {  # name: (probe, fast)
    "a_run_record_naming_a_yaml_runs_nothing": (a_run_record_naming_a_yaml_runs_nothing, False),
    "planted_links_are_not_written_through": (planted_links_are_not_written_through, False),
    "benchmark_namespace_out_of_its_data_path": (benchmark_namespace_out_of_its_data_path, False),
    "overwrite_keeps_the_users_logs": (overwrite_keeps_the_users_logs, False),
    "two_runs_into_one_directory": (two_runs_into_one_directory, True),
    "dated_directories_of_one_second": (dated_directories_of_one_second, True),
    "refused_commands_change_nothing": (refused_commands_change_nothing, False),
    "config_errors_name_the_key": (config_errors_name_the_key, True),
    "overwrite_leaves_no_old_logs": (overwrite_leaves_no_old_logs, True),
    "saved_dataset_behind_the_data_cache": (saved_dataset_behind_the_data_cache, False),
    "collapsed_stage_1": (collapsed_stage_1, True),
    "sigint_during_final_evaluation": (sigint_during_final_evaluation, False),
}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fast", action="store_true", help="only the probes that take a few seconds")
    parser.add_argument("--only", nargs="+", choices=sorted(PROBES), help="these probes")
    parser.add_argument("--list", action="store_true", help="list the probes and exit")
    parser.add_argument("--keep", action="store_true", help="keep each probe's folder (printed)")
    args = parser.parse_args(argv)
    if args.list:
        for name, (_, fast) in PROBES.items():
            print(f"{name}{'' if fast else '  (slow)'}")
        return 0
    names = args.only or [n for n, (_, fast) in PROBES.items() if fast or not args.fast]
    failures = 0
    for name in names:
        tmp = Path(tempfile.mkdtemp(prefix=f"probe_{name}_"))
        t0 = time.perf_counter()
        try:
            detail = PROBES[name][0](tmp)
            status = "PASS"
        except (ProbeFailed, subprocess.TimeoutExpired, OSError, KeyError, ValueError) as err:
            detail, status = f"{type(err).__name__}: {err}", "FAIL"
            failures += 1
        print(f"{status}  {name:<38} {time.perf_counter() - t0:5.1f} s  {detail}", flush=True)
        if args.keep:
            print(f"      kept: {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    print(f"{len(names) - failures} of {len(names)} probes passed")
    return failures


if __name__ == "__main__":
    sys.exit(main())
