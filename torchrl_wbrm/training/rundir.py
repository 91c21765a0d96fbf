"""Run directories: one run at a time per directory, and no run replaced unless asked.

* :func:`claim_run_dir` — an exclusive advisory lock on the directory itself, held for the run (nothing is written
  for it; the kernel drops it when the process ends).
* :func:`check_run_dir` — a new run refuses a directory holding a checkpoint or results unless ``overwrite=true``,
  which removes every output of the earlier run (:func:`clear_run_outputs`), and only those: the names a run of
  this project writes (a multi-seed run's ``seed<s>/`` folders included), never the user's own files.
* :func:`refuse_links` — a run never writes through a symbolic link: a folder it writes into (``logs/``, ``.hydra/``,
  ``wandb/``, ``seed<s>/``) or a file it appends to that is a link is refused before anything is written.
"""
from __future__ import annotations

import errno
import os
import re
import shutil
import sys
import time
from pathlib import Path

try:  # advisory locks (POSIX); without them a run directory is not locked
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

from torchrl_wbrm.keys import CHECKPOINT, HISTORY, RESULTS

__all__ = ["HYDRA_RECORD", "RUN_FILES", "RUN_OUTPUTS", "SEED_DIR", "RunDirClaim", "RunDirInUse", "check_run_dir",
           "claim_run_dir", "clear_run_outputs", "default_run_dir", "given_claim", "holds_run", "linked_outputs", "refuse_links",
           "remove_empty", "unique_dir"]


#: Files that mark a directory as holding a run.
RUN_FILES = (CHECKPOINT, RESULTS)


#: What a run writes into its directory (besides Hydra's record): removed by ``overwrite=true`` so that no output of
#: the earlier run (its CSV logs above all, which torchrl's ``CSVLogger`` would append to) outlives it.
RUN_OUTPUTS = (CHECKPOINT, "checkpoint.tmp", RESULTS, "results.json.tmp", HISTORY, "history.json.tmp",
               "training_curve.png", "evaluation.png", "logs", "wandb")


#: Hydra's record of the command that made the run (``.hydra/``).
HYDRA_RECORD = (".hydra",)


#: A multi-seed run's folder of one seed (``seeds=[...]``: ``<run dir>/seed<s>``).
SEED_DIR = re.compile(r"seed[0-9]+")


#: What a run writes into (folders, and files it appends to): never a symbolic link (:func:`refuse_links`). The
#: files a run replaces whole (``results.json``, ``checkpoint.pt``, ...) are renamed over their name, which replaces
#: a link there, not its target; their temporaries are created fresh.
WRITTEN_INTO = ("logs", "wandb", *HYDRA_RECORD)


def holds_run(run_dir: Path) -> list[str]:
    """The files of :data:`RUN_FILES` (and ``history.json``) in ``run_dir`` and in its ``seed<s>/`` folders (a
    multi-seed run's, finished or interrupted), if any of :data:`RUN_FILES` is among them."""
    run_dir = Path(run_dir)
    present = [name for name in (*RUN_FILES, HISTORY) if (run_dir / name).exists()]
    for seed_dir in _seed_dirs(run_dir):
        present += [f"{seed_dir.name}/{name}" for name in RUN_FILES if (seed_dir / name).exists()]
    return present if any(name.rsplit("/", 1)[-1] in RUN_FILES for name in present) else []


def _seed_dirs(run_dir: Path) -> list[Path]:
    """A multi-seed run's ``seed<s>/`` folders in ``run_dir`` (real folders, not links)."""
    if not run_dir.is_dir():
        return []
    return sorted(p for p in run_dir.iterdir() if SEED_DIR.fullmatch(p.name) and p.is_dir() and not p.is_symlink())


def _own_output(path: Path) -> bool:
    """Whether ``path`` is not one of this process's own open standard streams (a command's redirected output,
    ``> run/x.log``, is never removed by the command itself)."""
    try:
        st = os.stat(path, follow_symlinks=False)
    except OSError:
        return True
    for stream in (sys.stdout, sys.stderr):
        try:
            fd = stream.fileno()
            other = os.fstat(fd)
        except (AttributeError, OSError, ValueError):
            continue
        if (other.st_dev, other.st_ino) == (st.st_dev, st.st_ino):
            return False
    return True


def clear_run_outputs(run_dir: Path, *, hydra_record: bool = False, job_name: str | None = None) -> list[str]:
    """Remove the earlier run's outputs from ``run_dir``: :data:`RUN_OUTPUTS`, a multi-seed run's ``seed<s>/``
    folders (their outputs, then the folder if nothing else is left in it), and with ``hydra_record`` its ``.hydra/``
    record and Hydra's job log ``<job_name>.log`` (unless it is this command's own redirected output). Every other
    file is left alone (a user's ``notes.log`` too); a link is removed, never followed. Returns what was removed."""
    run_dir = Path(run_dir)
    names = list(RUN_OUTPUTS)
    if hydra_record:
        names += [*HYDRA_RECORD, *([f"{job_name}.log"] if job_name else [])]
    removed = []
    for name in names:
        path = run_dir / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif (path.exists() or path.is_symlink()) and _own_output(path):
            path.unlink()
        else:
            continue
        removed.append(name)
    for seed_dir in _seed_dirs(run_dir):
        inner = clear_run_outputs(seed_dir, hydra_record=hydra_record, job_name=job_name)
        removed += [f"{seed_dir.name}/{name}" for name in inner]
        remove_empty(seed_dir)
    return removed


def linked_outputs(run_dir: Path) -> list[Path]:
    """The symbolic links among what a run in ``run_dir`` writes into (:data:`WRITTEN_INTO`, in ``run_dir`` and in
    each ``seed<s>/`` folder, searched without following links), and ``seed<s>`` folders that are links."""
    run_dir = Path(run_dir)
    found = []
    roots = [run_dir]
    if run_dir.is_dir():
        for p in run_dir.iterdir():
            if SEED_DIR.fullmatch(p.name):
                if p.is_symlink():
                    found.append(p)
                elif p.is_dir():
                    roots.append(p)
    for root in roots:
        for name in WRITTEN_INTO:
            path = root / name
            if path.is_symlink():
                found.append(path)
            elif path.is_dir():
                for folder, dirs, files in os.walk(path):
                    found += [Path(folder) / n for n in (*dirs, *files) if (Path(folder) / n).is_symlink()]
    return found


def refuse_links(run_dir: Path) -> None:
    """Refuse, in one line naming it, a run directory where something the run writes into is a symbolic link
    (:func:`linked_outputs`): a run writes in its own directory only, never through a link to elsewhere."""
    links = linked_outputs(run_dir)
    if links:
        target = os.readlink(links[0])
        raise ValueError(
            f"{links[0]} is a symbolic link (to {target}): a run writes only into its own directory, never through a "
            f"link. Remove the link{'s' if len(links) > 1 else ''} ({len(links)} found), or choose another directory.")


def check_run_dir(run_dir: Path, *, overwrite: bool, remove: bool = True) -> None:
    """Refuse a new run into a directory that already holds a run, unless ``overwrite`` (then, with ``remove``,
    every output of the earlier run is removed: :func:`clear_run_outputs`)."""
    present = holds_run(run_dir)
    if not present:
        return
    if not overwrite:
        raise FileExistsError(
            f"{run_dir} already holds a run ({', '.join(present)}). Continue it with resume={run_dir}, choose another "
            f"directory, or pass overwrite=true to replace it."
        )
    if remove:
        clear_run_outputs(run_dir)


class RunDirInUse(RuntimeError):
    """Another run holds the run directory (:func:`claim_run_dir`)."""


class RunDirClaim:
    """An exclusive claim on a run directory: ``fcntl.flock`` on the directory's own file descriptor.

    Nothing is written for it, and the kernel drops it when the process ends, so a killed run leaves no stale lock.
    Released by :meth:`release` (or when this object is collected).
    """

    def __init__(self, path: Path, fd: int | None) -> None:
        self.path, self._fd = Path(path), fd

    @property
    def held(self) -> bool:
        return self._fd is not None

    def release(self) -> None:
        fd, self._fd = self._fd, None
        if fd is not None and fd >= 0:
            os.close(fd)  # closing the descriptor drops its lock

    def check_present(self) -> None:
        """Raise ``FileNotFoundError`` naming the directory if the claimed directory was removed, or replaced by
        another, while the run held it: a run never writes its files into a directory made anew under that name."""
        if self._fd is None or self._fd < 0:
            return
        held = os.fstat(self._fd)
        try:
            now = os.stat(self.path)
        except OSError:
            now = None
        if held.st_nlink == 0 or now is None or (now.st_dev, now.st_ino) != (held.st_dev, held.st_ino):
            raise FileNotFoundError(f"The run directory {self.path} was removed (or replaced) while the run held it; "
                                    f"its outputs are not written into another directory of that name. Start the run "
                                    f"again.")

    def __del__(self) -> None:
        self.release()

    def __repr__(self) -> str:
        return f"RunDirClaim({str(self.path)!r}, held={self.held})"


def claim_run_dir(run_dir: str | os.PathLike) -> RunDirClaim:
    """Claim the existing directory ``run_dir`` for one run, or raise :class:`RunDirInUse` if another run (in this
    process or another) holds it. Two runs can then never write one directory: the claim is taken before the
    directory is checked for an earlier run and held until the run ends."""
    path = Path(run_dir)
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    if fcntl is None:  # pragma: no cover - no advisory locks on this platform
        os.close(fd)
        return RunDirClaim(path, -1)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as err:
        os.close(fd)
        if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            raise RunDirInUse(
                f"{path} is in use by another run (it holds the directory's lock until it ends). Wait for that run "
                f"to end, or choose another directory (hydra.run.dir=...)."
            ) from err
        return RunDirClaim(path, -1)  # a file system without flock: unlocked, as before
    return RunDirClaim(path, fd)


def given_claim(claim: RunDirClaim | None, run_dir: str | os.PathLike) -> RunDirClaim | None:
    """``claim`` where it is a held claim of ``run_dir`` (``None``: none given or no longer held); a claim of another
    directory is refused."""
    if claim is None or not claim.held:
        return None
    if os.path.realpath(claim.path) != os.path.realpath(run_dir):
        raise ValueError(f"claim= holds {claim.path}, not this run's directory {run_dir}.")
    return claim


def default_run_dir(cfg, root: str | os.PathLike = "outputs/wbrm_offline") -> Path:
    """A new run directory named as the recipe names its own, ``<root>/<env.name>/<%Y-%m-%d_%H-%M-%S>_seed<seed>``,
    created with one exclusive ``mkdir`` (``..._1``, ``..._2``, ... when it exists: two runs started in the same
    second get directories of their own)."""
    return unique_dir(Path(root) / cfg.env.name / f"{time.strftime('%Y-%m-%d_%H-%M-%S')}_seed{cfg.seed}")


def unique_dir(path: Path) -> Path:
    """Create ``path`` (or ``path_1``, ``path_2``, ... if it exists) with one exclusive ``mkdir`` each: two runs that
    start in the same second get directories of their own."""
    path.parent.mkdir(parents=True, exist_ok=True)
    for i in range(1000):
        candidate = path if i == 0 else path.with_name(f"{path.name}_{i}")
        try:
            candidate.mkdir()
            return candidate
        except FileExistsError:
            continue
    raise FileExistsError(f"Could not create a fresh run directory next to {path} (1,000 of them exist).")


def remove_empty(path: Path) -> None:
    try:
        path.rmdir()
    except OSError:
        pass
