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
  taken over;
- ``.wvr-out.json`` records which command wrote the folder: a run refuses a folder another
  command wrote, a finished one of its own kind (unless the kind continues its folders: a
  sweep's ``--resume``) and a non-empty one no wvr run wrote, so no result is ever overwritten;
  a killed run's folder of its own kind is emptied first, so no leftover passes for this run's.

The marker is the one mechanism, rather than a temporary sibling renamed at the end, because a
killed sweep resumes in its own folder (``--resume``) and a recording is read while it grows.
This lives in ``kinematics`` only because every package may import it (the import rule).
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import sys
import time
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

INCOMPLETE = "INCOMPLETE"
LOCK = ".wvr-lock"
#: What wrote the folder: {"kind": the command, "command": its line, "started", "pid", "run": an id}.
KIND_FILE = ".wvr-out.json"

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


def writing(folder: str | Path) -> bool:
    """Whether this process is writing ``folder`` now (inside an :func:`output_folder` block)."""
    return Path(folder).resolve() in _ACTIVE


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
    name = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "python"
    if name == "__main__.py":                   # python -m wvr: name the package, as the user knows it
        name = Path(sys.argv[0]).parent.name
    args = [name] + sys.argv[1:] if sys.argv else [name]
    text = " ".join(args)
    return text if len(text) <= 120 else text[:117] + "..."


def _read_kind(folder: Path) -> dict | None:
    """The record of the wvr run that wrote ``folder`` (its KIND_FILE), or None without one."""
    try:
        text = (folder / KIND_FILE).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None if not (folder / KIND_FILE).exists() else {"kind": "?", "command": "an unreadable " + KIND_FILE}
    try:
        doc = json.loads(text)
    except ValueError:
        doc = None
    if not isinstance(doc, dict) or not isinstance(doc.get("kind"), str):
        return {"kind": "?", "command": "a damaged " + KIND_FILE}
    return doc


def _describe(doc: dict) -> str:
    cmd = doc.get("command")
    return f"wvr {doc['kind']}" + (f" ({cmd}" + (f", {doc['started']}" if doc.get("started") else "") + ")"
                                   if isinstance(cmd, str) else "")


def _judge(path: Path, kind: str, flag: str, reuse: bool, locked: bool = False) -> bool:
    """Whether a run of ``kind`` may write into ``path`` (read only): True when it must first
    clear what a killed run of its kind left; OutputFolderError (one line) when it may not."""
    if not path.is_dir():
        return False
    entries = sorted(p.name for p in path.iterdir() if p.name != LOCK)
    if not entries:
        return False
    holder = None if locked else _holder(path)     # (our own lock would read as another's)
    if holder is not None:
        raise OutputFolderError(f"{flag} {path}: another run is writing into this folder ({holder}); wait for it "
                                f"to finish, or choose another {flag}")
    doc = _read_kind(path)
    if doc is None:
        shown = ", ".join(entries[:3]) + (", ..." if len(entries) > 3 else "")
        raise OutputFolderError(f"{flag} {path}: is not empty and no wvr run wrote it (it holds {shown}); give "
                                f"another {flag} (a new or empty folder), or move those files away")
    if doc["kind"] != kind:
        raise OutputFolderError(f"{flag} {path}: holds the results of another command, {_describe(doc)}; give "
                                f"another {flag}, or delete {path} first")
    if reuse:
        return False            # the kind's own check decides (a sweep resumes, a HIL session is reused)
    if (path / INCOMPLETE).exists():
        return True
    raise OutputFolderError(f"{flag} {path}: already holds the finished results of {_describe(doc)}; give "
                            f"another {flag}, or delete {path} first to run it again")


def check_folder(path: str | Path, kind: str, flag: str = "--out", reuse: bool = False) -> Path:
    """Refuse, before any work and without touching anything, an output folder a run of
    ``kind`` (the command, e.g. "slam") may not write: one :func:`check_output` refuses, one
    another command or another run wrote, one no wvr run wrote that is not empty, one a live
    process writes. A folder a killed run of the same kind left is accepted (:func:`output_folder`
    clears it). Returns the path."""
    path = check_output(path, flag)
    _judge(path, kind, flag, reuse)
    return path


def check_output_file(path: str | Path, flag: str = "--out", suffix: str | None = None) -> Path:
    """Refuse, before any work, an output file that cannot be written: an existing folder, a
    missing folder to write it in, a parent that is a file or not writable, or (with
    ``suffix``, e.g. ".toml") another suffix. Returns the path; nothing is created."""
    path = Path(path)
    if path.is_dir():
        raise OutputFolderError(f"{flag} {path}: is a folder; give the path of the file to write (e.g. "
                                f"{path / ('out' + (suffix or ''))})")
    if suffix is not None and path.suffix.lower() != suffix:
        raise OutputFolderError(f"{flag} {path}: give a file name ending in {suffix}")
    parent = path.parent
    if parent.exists() and not parent.is_dir():
        raise OutputFolderError(f"{flag} {path}: {parent} is a file, not a folder; choose another {flag}")
    if not parent.exists():
        raise OutputFolderError(f"{flag} {path}: the folder {parent} does not exist; create it first or choose "
                                f"another {flag}")
    if not os.access(parent, os.W_OK | os.X_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise OutputFolderError(f"{flag} {path}: cannot be written there; choose a {flag} you can write to")
    return path


def _clear(path: Path, kind: str, flag: str, say: Callable[[str], None]) -> None:
    """Empty a folder a killed run of ``kind`` left (everything but our lock), saying so."""
    entries = [p for p in path.iterdir() if p.name != LOCK]
    for p in entries:
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()
    say(f"{flag} {path}: a killed wvr {kind} run left it incomplete; removed its {len(entries)} files and "
        f"folders before this run writes it")


def _nothing_written(folder: Path) -> bool:
    """Whether ``folder`` holds no file but our own markers (empty folders do not count)."""
    for root, _, files in os.walk(folder):
        if any(not (Path(root) == folder and f in (INCOMPLETE, LOCK, KIND_FILE)) for f in files):
            return False
    return True


def _stderr(text: str) -> None:
    print(f"wvr: {text}", file=sys.stderr, flush=True)


class OutputFolder:
    """A result folder being written: checked, created, locked, marked with its kind and
    INCOMPLETE, until :meth:`close` (see :func:`output_folder`, the usual way in).

    kind : the command writing it ("slam", "sim run", "recording"...), recorded in KIND_FILE;
        a folder another kind wrote is refused, and so is a finished one of the same kind unless
        ``reuse`` (a kind that continues its own folder: a sweep's --resume, which its ``check``
        judges). A killed run's folder of the same kind is emptied first (one line on stderr).
    """

    def __init__(self, path: str | Path, flag: str = "--out", check: Callable[[Path], None] | None = None,
                 kind: str = "results", reuse: bool = False, say: Callable[[str], None] = _stderr):
        path = check_output(path, flag)
        self.path, self._flag, self._fd = path, flag, None
        self._key = path.resolve()
        self.nested = self._key in _ACTIVE
        if self.nested:
            return
        self._created = not path.exists()
        _judge(path, kind, flag, reuse)      # before anything is made or locked: a refusal changes nothing
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise OutputFolderError(f"{flag} {path}: cannot create it ({e.strerror or e}); choose a {flag} folder "
                                    f"you can write to") from None
        try:
            self._fd = _take_lock(path, flag)
            if _judge(path, kind, flag, reuse, locked=True):   # again under the lock: the folder may have changed
                _clear(path, kind, flag, say)
            self._before = {p.name for p in path.iterdir()}   # what a refusal or a failure leaves as it was
            if check is not None:
                check(path)
            (path / KIND_FILE).write_text(json.dumps({
                "kind": kind, "command": _command(), "started": time.strftime("%Y-%m-%d %H:%M:%S"),
                "pid": os.getpid(), "run": uuid.uuid4().hex}) + "\n")
            (path / INCOMPLETE).write_text(
                f"{_command()}\nstarted {time.strftime('%Y-%m-%d %H:%M:%S')} by pid {os.getpid()}; this file is "
                f"removed when the run finishes, so while it is here the folder is not complete\n")
        except BaseException as e:
            self._undo()
            if isinstance(e, OSError):
                raise OutputFolderError(f"{flag} {path}: cannot write into it ({e.strerror or e}); choose a {flag} "
                                        f"folder you can write to") from None
            raise
        _ACTIVE.add(self._key)

    def _undo(self) -> None:
        """Leave the folder as it was found: a new one removed, an existing one without our files
        (and, if it was empty, without the empty folders made in it)."""
        if self._fd is not None:
            for name in (INCOMPLETE, KIND_FILE):
                if name not in getattr(self, "_before", ()):
                    (self.path / name).unlink(missing_ok=True)
            if not (getattr(self, "_before", {LOCK}) - {LOCK}):
                for p in self.path.iterdir():
                    if p.is_dir() and not p.is_symlink():
                        shutil.rmtree(p, ignore_errors=True)
            _release(self.path, self._fd)
            self._fd = None
        if self._created:
            shutil.rmtree(self.path, ignore_errors=True)

    def close(self, complete: bool = True) -> None:
        """End the write: complete removes INCOMPLETE; otherwise the marker stays (readers refuse
        the folder), except that a folder nothing was written into goes back to how it was."""
        if self.nested or self._fd is None:
            return
        _ACTIVE.discard(self._key)
        if complete:
            (self.path / INCOMPLETE).unlink(missing_ok=True)
            _release(self.path, self._fd)
            self._fd = None
        elif not (self._before - {LOCK}) and _nothing_written(self.path):
            self._undo()            # it was empty and no file was written: as it was
        else:
            _release(self.path, self._fd)
            self._fd = None


@contextmanager
def output_folder(path: str | Path, flag: str = "--out", check: Callable[[Path], None] | None = None,
                  kind: str = "results", reuse: bool = False) -> Iterator[Path]:
    """Write a result folder: checked and created, locked, marked with its kind and INCOMPLETE
    until the block ends.

    kind, reuse : see :class:`OutputFolder` (what may be written into, what a killed run left).
    check : called with the folder once the lock is held and before the marker is written, to
        refuse what is there (a sweep without --resume into a finished sweep): a refusal leaves
        an existing folder exactly as it was.
    On normal exit the marker is removed (the folder is complete) and the lock released. On an
    exception the marker stays (a folder nothing was written into goes back to how it was: one
    this call created is removed), so readers refuse what was left. Nested use on the same
    folder (a command around a runner) is one write: the outer block owns the marker, the lock
    and the check.
    """
    folder = OutputFolder(path, flag, check=check, kind=kind, reuse=reuse)
    try:
        yield folder.path
    except BaseException:
        folder.close(complete=False)
        raise
    folder.close(complete=True)


def _release(folder: Path, fd: int) -> None:
    try:
        (folder / LOCK).unlink(missing_ok=True)
    finally:
        os.close(fd)   # closing drops the flock
