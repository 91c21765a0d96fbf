"""Scale-out run for real: a two-job Hydra multirun of recipes/wbrm_offline.py through the Ray launcher, on a local
Ray cluster this test starts (``ray start --head``) and stops, and through submitit's local executor (the job files
Slurm would run), each with the sweep's table over seeds (``recipes/summarise.py``). Tiny budgets (tests/test_recipes.py's);
the cluster start is most of the cost.

The Ray driver is a ``python`` of its own (it joins the cluster, which the fixture then stops); the submitit sweep's
driver runs in the test process, and its two jobs are processes of their own, as Slurm's would be.

Both launchers are in the dev install (pyproject.toml); without them these tests skip and say so.
"""
from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import math
import os
import re
import runpy
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from tests.test_recipes import ROOT, TINY_LQR, run_recipe

pytestmark = [pytest.mark.launchers, pytest.mark.slow]

RAY_CLI = Path(sys.executable).with_name("ray")
START_TIMEOUT_S = 120


def _require(module: str, package: str) -> None:
    if importlib.util.find_spec(module) is None:
        pytest.skip(f"{package} is not installed (pip install -e '.[dev]' or '.[sweeps]')")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _check_two_results(sweep_dir: Path) -> list[dict]:
    paths = sorted(sweep_dir.rglob("results.json"))
    assert len(paths) == 2, paths
    results = [json.loads(p.read_text()) for p in paths]
    assert sorted(r["seed"] for r in results) == [0, 1]
    for r in results:
        assert r["status"] == "finished", r["status"]
        assert r["env"] == "lqr_exp1"
        for key in ("regret", "regret_ci", "return", "q_error_expert", "q_error_behaviour"):
            assert math.isfinite(r["final"][key]), (key, r["final"][key])
    # the sweep's table over seeds (recipes/summarise.py, as a user runs it after a multirun)
    out, argv = io.StringIO(), sys.argv
    sys.argv = ["summarise.py", str(sweep_dir), "--group-by", "ratio.source"]
    try:
        with contextlib.redirect_stdout(out):
            runpy.run_path(str(ROOT / "recipes" / "summarise.py"), run_name="__main__")
    finally:
        sys.argv = argv
    row = [line for line in out.getvalue().splitlines() if line.startswith("| none")][0]
    assert "| 2 |" in row and "±" in row  # two seeds, a confidence interval
    return results


@pytest.fixture
def ray_cluster():
    """A one-node Ray cluster (2 CPUs) on free local ports, stopped afterwards even when the test fails.

    ``ray start --block`` keeps the CLI in the foreground, in a session of its own: the teardown signals it (it then
    stops the processes it started) and kills whatever is left of that session, so no other Ray on the machine is
    touched (``ray stop`` would stop every one).
    """
    _require("ray", "ray")
    _require("hydra_plugins.hydra_ray_launcher", "hydra-ray-launcher")
    assert RAY_CLI.is_file(), f"no ray CLI beside {sys.executable}"
    # Ray's unix sockets live under the temp dir and their paths must stay under 107 bytes: a short dir in /tmp
    temp_dir = tempfile.mkdtemp(prefix="ray", dir="/tmp")
    port = _free_port()
    log_path = Path(temp_dir) / "ray_start.log"
    # the job processes are Ray workers, started by this cluster's raylet with its environment
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg", "WANDB_MODE": "offline",
           "RAY_USAGE_STATS_ENABLED": "0"}
    cmd = [str(RAY_CLI), "start", "--head", "--block", "--num-cpus=2", "--node-ip-address=127.0.0.1",
           f"--port={port}", f"--temp-dir={temp_dir}", "--include-dashboard=false",
           f"--dashboard-port={_free_port()}", f"--ray-client-server-port={_free_port()}", "--disable-usage-stats"]
    with open(log_path, "w") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    try:
        deadline = time.monotonic() + START_TIMEOUT_S
        while "Ray runtime started" not in log_path.read_text():
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"ray start did not come up (rc {proc.poll()}):\n{log_path.read_text()[-3000:]}")
            time.sleep(0.2)
        yield SimpleNamespace(address=f"127.0.0.1:{port}", temp_dir=Path(temp_dir))
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                pass
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # gcs_server, raylet, agents, workers: all in the CLI's session
        except ProcessLookupError:
            pass
        proc.wait(timeout=10)
        shutil.rmtree(temp_dir, ignore_errors=True)


def test_multirun_on_a_local_ray_cluster(tmp_path, ray_cluster):
    proc = run_recipe(
        "wbrm_offline.py", "-m", "hydra/launcher=ray", f"hydra.launcher.ray.init.address={ray_cluster.address}",
        # the launcher sets a default object_store_memory, which ray.init refuses when it joins a running cluster
        "+hydra.launcher.ray.init.object_store_memory=null",
        "seed=0,1", "ratio.source=none", *TINY_LQR, "plots=false", "logger=none", f"hydra.sweep.dir={tmp_path}",
        process=True,
    )
    out = proc.stdout + proc.stderr
    # the driver joined the cluster the fixture started (Ray prints the node's own IP, so match the port)
    port = ray_cluster.address.rsplit(":", 1)[1]
    assert re.search(rf"Connecting to existing Ray cluster at address: [\w.]+:{port}\b", out), out[-3000:]
    assert "Ray Launcher is launching 2 jobs" in out
    # the jobs ran in this cluster's worker processes: each worker's stdout goes to its own file in the cluster's
    # log folder, written by the worker itself (the driver's echo of it, "(_run_job pid=...)", comes from Ray's log
    # monitor and can arrive after the driver has exited)
    workers = "".join(p.read_text(errors="replace")
                      for p in ray_cluster.temp_dir.glob("session_*/logs/worker-*.out"))
    assert workers.count(":task_name:_run_job") >= 2, workers[-3000:]
    _check_two_results(tmp_path)


def test_multirun_with_submitit_local(tmp_path):
    _require("hydra_plugins.hydra_submitit_launcher", "hydra-submitit-launcher")
    _require("submitit", "submitit")
    proc = run_recipe(
        "wbrm_offline.py", "-m", "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=5",
        "seed=0,1", "ratio.source=none", *TINY_LQR, "plots=false", "logger=none", f"hydra.sweep.dir={tmp_path}",
    )
    assert "Submitit 'local' sweep output dir" in proc.stdout + proc.stderr
    logs = sorted((tmp_path / ".submitit").glob("*/*_log.out"))
    assert len(logs) == 2 and all("Job completed successfully" in p.read_text() for p in logs), logs
    _check_two_results(tmp_path)
