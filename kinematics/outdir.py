"""Output folders that never look complete when they are not, and that one run writes at a time.

Every command that writes a folder (a sweep, a placement study, a recording, a SLAM run...)
writes it inside :func:`output_folder`:

- the folder is checked before any work starts: a path that is a file, or a place that cannot
  be written, is refused with a one-line :class:`OutputFolderError`;
- a marker file ``INCOMPLETE`` is written first and removed last, so a run that is killed or
  fails leaves a folder every reader refuses (:func:`check_complete`) instead of a shorter
  result that looks whole;
- a lock (``.wvr-lock``, an ``flock`` the kernel drops when the process dies) keeps a second run
  out of the folder while the first one writes it; a lock left by a dead process is simply
  taken over.

The marker is the one mechanism, rather than a temporary sibling renamed at the end, because a
killed sweep resumes in its own folder (``--resume``) and a recording is read while it grows.
This lives in ``kinematics`` only because every package may import it (the import rule).
"""

from __future__ import annotations

import fcntl
import os
import shutil
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

INCOMPLETE = "INCOMPLETE"
LOCK = ".wvr-lock"

#: Folders this process is writing now (resolved paths): a runner called inside a command that
#: already holds the folder just writes into it.
_ACTIVE: set[Path] = set()


class OutputFolderError(ValueError):
    """An output folder that cannot be written, or a result folder that is not complete; the
    message names the folder and what to do."""


def check_output(path: str | Path, flag: str = "--out") -> Path:
    """Refuse, before any work, an output folder that cannot be created or written.

    Returns the path. Raises :class:`OutputFolderError` when it is an existing file, when a
    parent is a file, or when the nearest existing parent is not a writable folder.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputFolderError(f"{flag} {path}: is a file, not a folder; give a folder for the results "
                                f"(a new name, or an existing folder)")
    parent = path
    while not parent.exists():
        if parent.parent == parent:
            break
        parent = parent.parent
    if parent.exists() and not parent.is_dir():
        raise OutputFolderError(f"{flag} {path}: {parent} is a file, so no folder can be made under it; "
                                f"choose another {flag}")
    if parent.exists() and not os.access(parent, os.W_OK | os.X_OK):
        raise OutputFolderError(f"{flag} {path}: {parent} is not writable; choose a {flag} folder you can write to")
    return path


def is_incomplete(folder: str | Path) -> bool:
    """Whether ``folder`` holds the INCOMPLETE marker of a run that has not finished."""
    return (Path(folder) / INCOMPLETE).exists()


def _holder(folder: Path) -> str | None:
    """A description of the live process writing ``folder`` ("pid 123, wvr sim record"), or
    None when no process holds its lock."""
    lock = folder / LOCK
    try:
        fd = os.open(lock, os.O_RDONLY)
    except OSError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            text = os.pread(fd, 400, 0).decode("utf-8", "replace").strip()
            return text or "another process"
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def check_complete(folder: str | Path, what: str = "folder") -> None:
    """Refuse a result folder whose writer has not finished (the INCOMPLETE marker is there).

    Raises :class:`OutputFolderError` saying whether the writer is still running or stopped
    before the end, and what to do.
    """
    folder = Path(folder)
    if not is_incomplete(folder):
        return
    holder = _holder(folder)
    if holder is not None:
        raise OutputFolderError(f"{folder}: this {what} is still being written ({holder}); wait for that run to "
                                f"finish, then use it")
    raise OutputFolderError(f"{folder}: this {what} is incomplete: the run writing it stopped before the end "
                            f"(killed or failed), so it may be shorter than it looks; run it again, or delete "
                            f"{folder / INCOMPLETE} to use what it holds")


def _take_lock(folder: Path, flag: str) -> int:
    """An open descriptor holding the folder's lock, or OutputFolderError naming the holder."""
    lock = folder / LOCK
    for _ in range(5):
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as e:
            raise OutputFolderError(f"{flag} {folder}: cannot write into it ({e.strerror or e}); choose a {flag} "
                                    f"folder you can write to") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            text = os.pread(fd, 400, 0).decode("utf-8", "replace").strip() or "another process"
            os.close(fd)
            raise OutputFolderError(f"{flag} {folder}: another run is writing into this folder ({text}); wait for it "
                                    f"to finish, or choose another {flag}") from None
        # The holder before us may have removed the file between our open and our lock: then the
        # lock we hold is on a name no one else sees, so take it again.
        try:
            same = os.stat(lock).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"pid {os.getpid()}, {_command()}, since {time.strftime('%H:%M:%S')}\n".encode(), 0)
            return fd
        os.close(fd)
    raise OutputFolderError(f"{flag} {folder}: could not take the folder's lock; try again")


def _command() -> str:
    args = [Path(sys.argv[0]).name] + sys.argv[1:] if sys.argv and sys.argv[0] else ["python"]
    text = " ".join(args)
    return text if len(text) <= 120 else text[:117] + "..."


@contextmanager
def output_folder(path: str | Path, flag: str = "--out",
                  check: Callable[[Path], None] | None = None) -> Iterator[Path]:
    """Write a result folder: checked and created, locked, marked INCOMPLETE until the block ends.

    check : called with the folder once the lock is held and before the marker is written, to
        refuse what is there (a sweep without --resume into a finished sweep): a refusal leaves
        an existing folder exactly as it was.
    On normal exit the marker is removed (the folder is complete) and the lock released. On an
    exception the marker stays (a folder this call created and nothing was written into is
    removed again), so readers refuse what was left. Nested use on the same folder (a command
    around a runner) is one write: the outer block owns the marker, the lock and the check.
    """
    path = check_output(path, flag)
    key = path.resolve()
    if key in _ACTIVE:
        yield path
        return
    created = not path.exists()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputFolderError(f"{flag} {path}: cannot create it ({e.strerror or e}); choose a {flag} folder "
                                f"you can write to") from None
    try:
        fd = _take_lock(path, flag)
    except OutputFolderError:
        if created:
            shutil.rmtree(path, ignore_errors=True)
        raise
    if check is not None:
        try:
            check(path)
        except BaseException:
            _release(path, fd)
            if created:
                shutil.rmtree(path, ignore_errors=True)
            raise
    marker = path / INCOMPLETE
    try:
        marker.write_text(f"{_command()}\nstarted {time.strftime('%Y-%m-%d %H:%M:%S')} by pid {os.getpid()}; this "
                          f"file is removed when the run finishes, so while it is here the folder is not complete\n")
    except OSError as e:
        _release(path, fd)
        raise OutputFolderError(f"{flag} {path}: cannot write into it ({e.strerror or e}); choose a {flag} folder "
                                f"you can write to") from None
    _ACTIVE.add(key)
    try:
        yield path
    except BaseException:
        _ACTIVE.discard(key)
        if created and {p.name for p in path.iterdir()} <= {INCOMPLETE, LOCK}:
            marker.unlink(missing_ok=True)
            _release(path, fd)
            shutil.rmtree(path, ignore_errors=True)
        else:
            _release(path, fd)
        raise
    _ACTIVE.discard(key)
    marker.unlink(missing_ok=True)
    _release(path, fd)


def _release(folder: Path, fd: int) -> None:
    try:
        (folder / LOCK).unlink(missing_ok=True)
    finally:
        os.close(fd)   # closing drops the flock
