"""Writing a file whole or not at all, and the kill tests' hook: the one writer of every file the package replaces.

* :func:`atomic_write` — a file is written to a temporary file created fresh (a stale one, or a symbolic link planted
  under its name, is unlinked first; then ``O_CREAT | O_EXCL | O_NOFOLLOW``), fsynced and renamed over the old one: a
  process killed at any point (SIGKILL included) leaves no half-written file, and nothing is ever written through a
  link.
* :func:`create_fresh` — that fresh creation, for any file a run writes.
* :func:`pause_for_test` — the point where a kill test stops a run (unset outside tests: nothing happens).
"""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

__all__ = ["TEST_PAUSE_ENV", "WriteFailed", "atomic_write", "create_fresh", "pause_for_test"]


#: The test hook's environment variable (:func:`pause_for_test`); outside tests it is unset and the hook does nothing.
TEST_PAUSE_ENV = "TORCHRL_WBRM_TEST_PAUSE_AT"


#: How many times this process has replaced each file name (:func:`atomic_write`), for the hook's ``<name>:<n>``.
_REPLACED: dict[str, int] = {}


def pause_for_test(point: str) -> None:
    """Test hook for kill tests: when the environment variable :data:`TEST_PAUSE_ENV` equals ``point``, print
    ``TORCHRL_WBRM_TEST_PAUSE_AT: paused at <point>`` on stderr and wait (for the test to kill the process).

    Points: ``<stage>:<step>`` after a training step (``ratio:15``, ``q:25``), and ``<file name>:<n>`` inside the
    n-th :func:`atomic_write` of that file in this process, after the new content is on disk in the temporary file and
    before it replaces the file (``checkpoint.pt:4``, ``results.json:1``). Unset, the hook does nothing."""
    if os.environ.get(TEST_PAUSE_ENV) != point:
        return
    print(f"{TEST_PAUSE_ENV}: paused at {point}", file=sys.stderr, flush=True)
    while True:
        time.sleep(60)


def _fsync_dir(directory: Path) -> None:
    """Make a rename in ``directory`` durable (where the platform lets a directory be opened and synced)."""
    try:
        fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


#: ``os.open`` flags of a file created fresh: never an existing file, never through a symbolic link
_FRESH = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)


def create_fresh(path: str | os.PathLike, mode: str = "wb"):
    """Open ``path`` for writing as a file created now: whatever is there under that name (a stale temporary file, a
    symbolic link pointing elsewhere) is unlinked first, never followed, and the file is created with
    ``O_CREAT | O_EXCL | O_NOFOLLOW``, so what is written lands in ``path``'s own folder and nowhere else. Returns
    the open file object (``mode``: ``"wb"`` or ``"w"``)."""
    path = Path(path)
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass
    fd = os.open(path, _FRESH, 0o644)
    return os.fdopen(fd, mode)


class WriteFailed(OSError):
    """A file could not be written (:func:`atomic_write`): the message names the file, why, and the free space on its
    disk; the partial temporary file is removed, and the file written before, if any, is kept whole."""

    def __init__(self, path: Path, err: BaseException) -> None:
        import shutil

        path = Path(path)
        reason = getattr(err, "strerror", None) or " ".join(str(err).split())[:160] or type(err).__name__
        try:
            usage = shutil.disk_usage(path.parent)
            disk = f"{usage.free / 2**20:.1f} MiB free of {usage.total / 2**20:.1f} MiB on the disk holding {path.parent}"
        except OSError:
            disk = f"{path.parent} cannot be read"
        self.message = (f"Could not write {path}: {reason} ({disk}); the partial file was removed and the earlier "
                        f"{path.name}, if any, is kept.")
        super().__init__(getattr(err, "errno", None) or 0, self.message)

    def __str__(self) -> str:
        return self.message


def atomic_write(path: Path, write, *, tmp: Path | None = None) -> None:
    """Replace ``path`` with what ``write(file)`` writes, atomically: the content goes to ``tmp`` (default
    ``<path>.tmp``, in the same directory), is flushed and fsynced, then renamed over ``path`` (``os.replace``) and
    the directory synced. A process killed at any point leaves either the old ``path`` or the new one complete, never
    a half-written one (at most a stale temporary file, which the next write replaces). The temporary file is created
    fresh (:func:`create_fresh`): a link planted under its name is removed, not written through, and the rename
    replaces a link at ``path`` itself, not its target."""
    path = Path(path)
    tmp = Path(tmp) if tmp is not None else path.with_name(path.name + ".tmp")
    if os.path.realpath(tmp.parent) != os.path.realpath(path.parent) or tmp.name in ("", ".", ".."):
        raise ValueError(f"atomic_write: the temporary file {tmp} must lie beside {path}, in its folder.")
    try:
        with create_fresh(tmp) as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
    except BaseException as err:
        try:
            os.unlink(tmp)  # no partial temporary file is left behind
        except OSError:
            pass
        if isinstance(err, (OSError, RuntimeError)):  # a full disk, a read-only one, a folder removed (torch.save)
            raise WriteFailed(path, err) from err
        raise
    _REPLACED[path.name] = _REPLACED.get(path.name, 0) + 1
    pause_for_test(f"{path.name}:{_REPLACED[path.name]}")
    os.replace(tmp, path)
    _fsync_dir(path.parent)
