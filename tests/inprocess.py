"""Run a recipe script the way ``python <script> <args>`` runs it, inside the test process.

A fresh ``python`` pays about 9 s of CPU to import torch, torchrl and Hydra before the recipe does anything; a test
worker has them imported already. :func:`run_script` executes the same file as ``__main__`` (:func:`runpy.run_path`)
with the command's ``sys.argv``, working directory and environment, captures what it writes to ``sys.stdout`` and
``sys.stderr``, and returns a :class:`subprocess.CompletedProcess` with the exit status ``python`` would give
(``SystemExit``'s code; 1 and the traceback on stderr for an uncaught exception). Whatever the run changes in the
process is put back afterwards: signal handlers, torch's thread count, warning filters and the libraries' log
levels.

What needs a process of its own stays a subprocess in the tests: signals sent from outside (SIGINT, SIGTERM,
SIGKILL), two runs at once, output written by C code or by handlers bound to the real streams, and at least one test
per command that starts it exactly as a user does.
"""
from __future__ import annotations

import contextlib
import io
import logging
import os
import runpy
import signal
import subprocess
import sys
import traceback
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_SIGNALS = tuple(s for s in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGUSR1", None)) if s is not None)


@contextlib.contextmanager
def _restored_process_state(cwd, env: dict | None):
    import torch

    from torchrl_wbrm._console import CHATTY_LOGGERS
    saved_env = dict(os.environ)
    saved_cwd = os.getcwd()
    saved_argv, saved_path = list(sys.argv), list(sys.path)
    handlers = {sig: signal.getsignal(sig) for sig in _SIGNALS}
    threads = torch.get_num_threads()
    levels = {name: logging.getLogger(name).level for name in (*CHATTY_LOGGERS, "hydra")}
    try:
        if env is not None:
            os.environ.clear()
            os.environ.update(env)
        os.chdir(cwd)
        with warnings.catch_warnings():
            yield
    finally:
        os.chdir(saved_cwd)
        os.environ.clear()
        os.environ.update(saved_env)
        sys.argv[:], sys.path[:] = saved_argv, saved_path
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
        torch.set_num_threads(threads)
        for name, level in levels.items():
            logging.getLogger(name).setLevel(level)


def _exit_code(code) -> tuple[int, str]:
    """``python``'s exit status for ``SystemExit(code)`` and what it prints (a message code goes to stderr)."""
    if code is None:
        return 0, ""
    if isinstance(code, int):
        return code, ""
    return 1, f"{code}\n"


def run_script(script: str | os.PathLike, *args: str, cwd=ROOT, env: dict | None = None) -> subprocess.CompletedProcess:
    """``python <script> <args>`` run in this process (see the module's docstring); ``env`` replaces the environment
    for the run when given."""
    script = str(Path(script) if Path(script).is_absolute() else ROOT / script)
    out, err = io.StringIO(), io.StringIO()
    with _restored_process_state(cwd, env):
        sys.argv[:] = [script, *map(str, args)]
        sys.path.insert(0, str(Path(script).parent))  # as python does: the script's folder first
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                runpy.run_path(script, run_name="__main__")
                code = 0
            except SystemExit as exit_:
                code, message = _exit_code(exit_.code)
                err.write(message)
            except BaseException:  # noqa: BLE001  (what python prints and returns for an uncaught exception)
                traceback.print_exc(file=err)
                code = 1
    return subprocess.CompletedProcess([sys.executable, script, *args], code, out.getvalue(), err.getvalue())


def recipe(*overrides: str, cwd=ROOT, env: dict | None = None) -> subprocess.CompletedProcess:
    """``python recipes/wbrm_offline.py <overrides>`` in this process."""
    return run_script(ROOT / "recipes" / "wbrm_offline.py", *overrides, cwd=cwd, env=env)
