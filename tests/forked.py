"""Start a recipe script as a process of its own, without paying for its imports again.

A test that sends a signal to a run, or runs two at once, needs the run in a process of its own; a fresh ``python``
pays about 5 s of CPU to import torch, torchrl, tensordict and Hydra before the script does anything.
:func:`popen_script` forks the process from a server that has imported them once per test worker (multiprocessing's
``forkserver``, whose preloaded modules are this package's command and its libraries, nothing run yet), so the child
starts where a fresh ``python`` would be after its imports. In the child the script runs as ``__main__``
(:func:`runpy.run_path`) with its own ``sys.argv``, environment and working directory, its file descriptors 1 and 2
on pipes the test reads, and its exit status what ``python <script>`` would return (a signal's negative number when
killed by one).

What must start exactly as a user types it (the printed resume command, the packaging test, at least one test per
command) still runs as a real ``python`` subprocess.
"""
from __future__ import annotations

import importlib.util
import multiprocessing
import os
import runpy
import subprocess
import sys
import tempfile
import threading
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: what the server imports once: the recipe's command module (torch, tensordict, torchrl, Hydra and the package)
PRELOAD = ["torchrl_wbrm.cli", "torchrl_wbrm.training.seeds", "matplotlib.pyplot"]

_context = None


def mark_pandas_absent() -> None:
    """Where pandas is not installed, say so in ``sys.modules`` (``None``), where :func:`importlib.util.find_spec`
    looks first; called by tests/conftest.py and in each forked child.

    tensordict asks ``find_spec("pandas")`` for every output a TensorDictModule writes (``TensorDict.from_any``);
    without pandas each call searches every path entry (and pytest's import hook) again, about 40 µs: measured here,
    8-15% of an IQL training step on LQR. The answer stays None, and ``import pandas`` still raises
    ModuleNotFoundError.
    """
    if "pandas" not in sys.modules and importlib.util.find_spec("pandas") is None:
        sys.modules["pandas"] = None


def _forkserver():
    global _context
    if _context is None:
        _context = multiprocessing.get_context("forkserver")
        _context.set_forkserver_preload(PRELOAD)
    return _context


def _child(script: str, args: list[str], cwd: str, env: dict, stdout_path: str, stderr_path: str) -> None:
    for fd, path in ((1, stdout_path), (2, stderr_path)):
        target = os.open(path, os.O_WRONLY)  # a pipe the test reads, or os.devnull
        os.dup2(target, fd)
        os.close(target)
    os.environ.clear()
    os.environ.update(env)
    mark_pandas_absent()
    os.chdir(cwd)
    sys.argv[:] = [script, *args]
    code = 0
    try:
        runpy.run_path(script, run_name="__main__")
    except SystemExit as exit_:
        if exit_.code is None:
            code = 0
        elif isinstance(exit_.code, int):
            code = exit_.code
        else:
            print(exit_.code, file=sys.stderr)
            code = 1
    except BaseException:  # noqa: BLE001  (what python prints and returns for an uncaught exception)
        traceback.print_exc()
        code = 1
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


class ForkedProcess:
    """The part of :class:`subprocess.Popen`'s interface the tests use, for a process :func:`popen_script` forked:
    ``pid``, ``poll``, ``wait``, ``send_signal``, ``kill``, ``communicate``, ``returncode`` and text ``stdout`` and
    ``stderr`` pipes."""

    def __init__(self, process, stdout, stderr, args):
        self._process = process
        self.stdout, self.stderr, self.args = stdout, stderr, args
        self.pid = process.pid

    @property
    def returncode(self):
        return self._process.exitcode

    def poll(self):
        return self._process.exitcode

    def wait(self, timeout: float | None = None) -> int:
        self._process.join(timeout)
        if self._process.exitcode is None:
            raise subprocess.TimeoutExpired(self.args, timeout)
        return self._process.exitcode

    def send_signal(self, sig: int) -> None:
        if self._process.exitcode is None:
            os.kill(self.pid, sig)

    def kill(self) -> None:
        self._process.kill()

    def communicate(self, timeout: float | None = None) -> tuple[str, str]:
        """Both pipes read to their end (each in its own thread, so that neither fills while the other is read)."""
        texts = {}
        readers = [threading.Thread(target=lambda name=name: texts.__setitem__(name, getattr(self, name).read()),
                                    daemon=True) for name in ("stdout", "stderr") if getattr(self, name) is not None]
        for reader in readers:
            reader.start()
        self.wait(timeout)
        for reader in readers:
            reader.join(timeout)
        return texts.get("stdout", ""), texts.get("stderr", "")


def popen_script(script: str | os.PathLike, *args: str, cwd=ROOT, env: dict | None = None,
                 stdout: bool = True) -> ForkedProcess:
    """``subprocess.Popen([python, script, *args], cwd=cwd, env=env, stdout=PIPE, stderr=PIPE, text=True)``, the
    process forked from the worker's preloaded server (see the module's docstring); ``stdout=False`` discards its
    standard output (``stdout=DEVNULL``), and the returned ``stdout`` is ``None``."""
    script = str(Path(script) if Path(script).is_absolute() else ROOT / script)
    fifo_dir = Path(tempfile.mkdtemp(prefix="forked_"))
    pipes = {name: str(fifo_dir / name) for name in (("stdout", "stderr") if stdout else ("stderr",))}
    for path in pipes.values():
        os.mkfifo(path)
    process = _forkserver().Process(
        target=_child, args=(script, [str(a) for a in args], str(cwd), dict(os.environ if env is None else env),
                             pipes.get("stdout", os.devnull), pipes["stderr"]),
        daemon=False)
    process.start()
    # opened after the start, in the child's order: each open waits for the child's end of the pipe
    streams = {name: open(path, encoding="utf-8") for name, path in pipes.items()}
    for path in pipes.values():
        os.unlink(path)
    os.rmdir(fifo_dir)
    return ForkedProcess(process, streams.get("stdout"), streams["stderr"], [sys.executable, script, *args])


def stop() -> None:
    """Stop the worker's fork server, if a test started one, and wait for it: its runs' CPU time then counts with
    this process's children (``/usr/bin/time`` and ``RUSAGE_CHILDREN`` count only processes waited for)."""
    if _context is not None:
        from multiprocessing import forkserver

        forkserver._forkserver._stop()


def run_forked(script: str | os.PathLike, *args: str, cwd=ROOT, env: dict | None = None,
               timeout: float = 300.0) -> subprocess.CompletedProcess:
    """``subprocess.run([python, script, *args], capture_output=True, text=True)`` through :func:`popen_script`."""
    proc = popen_script(script, *args, cwd=cwd, env=env)
    out, err = proc.communicate(timeout)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
