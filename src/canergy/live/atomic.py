"""Files that survive ``kill -9`` and power loss: write a temporary, fsync, rename, fsync the
directory. A reader sees the old content or the new, never a mix."""

from __future__ import annotations

import contextlib
import gc
import json
import os
import stat
import sys
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")


def check_writable_dir(path: Path, what: str) -> None:
    """Fail now, naming ``what`` and the directory, if ``path`` could not be written atomically
    later (each write creates a temporary file beside it)."""
    folder = path.parent
    if not folder.is_dir():
        raise FileNotFoundError(f"cannot write {what} {path}: no directory {folder}")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise PermissionError(f"cannot write {what} {path}: directory {folder} is not writable")
    if path.is_dir():
        raise IsADirectoryError(f"cannot write {what} {path}: it is a directory")


NO_FSYNC_WARNING = (
    "--no-fsync: records are not synced to disk; a power cut can leave an older image of them, "
    "which this run's promises no longer cover (for tests only)"
)


def warn_no_fsync(prog: str, no_fsync: bool) -> None:
    """Say on stderr, once at start, that this run's records are not synced (``--no-fsync``)."""
    if no_fsync:
        print(f"{prog}: warning: {NO_FSYNC_WARNING}", file=sys.stderr, flush=True)


def check_private_dir(path: Path, what: str) -> None:
    """Fail, naming ``what`` and the directory, if someone other than root and this user could
    replace or roll back ``path`` (as sshd's StrictModes): its directory, or one above it, is
    writable by group or others without the sticky bit (``/tmp`` is fine), or belongs to another
    user. A writer of the directory can rename an old copy over the file, or (without a key) an
    edited one. The directories are checked as written, with their symlinks resolved, and those
    of the file's own target when ``path`` is a symlink (a key linked from a private folder into
    an open one is as open as its target's folder)."""
    me = os.geteuid()
    whole = Path(os.path.abspath(path))
    folder = whole.parent
    seen: set[Path] = set()
    for top in (folder, folder.resolve(), Path(os.path.realpath(whole)).parent):
        for d in (top, *top.parents):
            if d in seen:
                continue
            seen.add(d)
            st = os.stat(d)
            if st.st_uid not in (0, me):
                raise PermissionError(
                    f"{what} {path}: directory {d} belongs to user {st.st_uid}, who can replace "
                    "or roll back the file; use a directory of root's or your own"
                )
            if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH) and not st.st_mode & stat.S_ISVTX:
                raise PermissionError(
                    f"{what} {path}: directory {d} (mode {stat.S_IMODE(st.st_mode):04o}) is "
                    f"writable by others, who can replace or roll back the file; chmod go-w {d}"
                )


def same_file(a: Path, b: Path) -> bool:
    """``a`` and ``b`` name one file: the same path once relative parts and symlinks are
    resolved, or (both existing) the same inode, as hard links are."""
    if a.resolve() == b.resolve():
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist (yet)
        return False


def write_atomic(path: Path, data: bytes, *, fsync: bool = True, mode: int | None = None) -> None:
    """Replace ``path`` with ``data`` through a temporary beside it. ``mode``: the temporary is
    new (a stale one is removed) and has exactly this mode, whatever the umask, before a byte
    goes in (0o600 for a file only its owner may read or write)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with contextlib.suppress(FileNotFoundError):
        os.unlink(tmp)
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL
    fd = os.open(tmp, flags, 0o666 if mode is None else mode)
    with os.fdopen(fd, "wb") as f:
        if mode is not None:
            os.fchmod(fd, mode)
        f.write(data)
        if fsync:
            f.flush()
            os.fsync(f.fileno())
    os.replace(tmp, path)
    if fsync:
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)


def write_json_atomic(path: Path, obj: Any, *, fsync: bool = True) -> None:
    write_atomic(path, (json.dumps(obj, indent=1, sort_keys=True) + "\n").encode(), fsync=fsync)


class RecordInUse(OSError):
    """Another holder keeps the record: two writers of one record would both spend it."""


def lock_path(path: Path) -> Path:
    """The lock file of the record ``path``: beside it, never replaced (the record is, by each
    atomic write, so a lock on the record itself would guard a file already gone)."""
    return path.with_name(f".{path.name}.lock")


class RecordLock:
    """An exclusive ``flock`` on a record's lock file, taken before the record is read and
    held until ``release`` or until the object that keeps the record (``bind``) is collected.
    ``flock`` locks conflict between two opens of the file, so a second holder is refused in
    another process and in this one."""

    def __init__(self, path: Path, what: str, *, in_place: bool = False, hint: str = "") -> None:
        """``in_place``: the record is written in place, never replaced (an NV file): its
        own file is locked, as the C ports lock theirs. ``hint``: what the refusal adds."""
        self.path = path if in_place else lock_path(path)
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        except OSError as exc:
            raise RecordInUse(f"cannot lock {what} {path}: {self.path}: {exc.strerror}") from exc
        if not _flock(fd):
            gc.collect()  # a holder in this process no longer referenced lets go when collected
            if not _flock(fd):
                holder = "" if in_place else os.pread(fd, 32, 0).decode("ascii", "replace")
                os.close(fd)
                who = f"pid {holder.strip()}; " if holder.strip() else ""
                raise RecordInUse(
                    f"{what} {path} is kept by another holder ({who}lock {self.path}): two "
                    f"holders of one record would both spend what it holds; stop the other{hint}"
                )
        if not in_place:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd

    def bind(self, owner: object) -> None:
        """Hold the lock as long as ``owner`` (what keeps the record) lives."""
        weakref.finalize(owner, os.close, self._fd)

    def release(self) -> None:
        """Let go of the record now (before ``bind``: the record was not taken)."""
        os.close(self._fd)


def kept_by(
    path: Path, what: str, make: Callable[[], T], *, in_place: bool = False, hint: str = ""
) -> T:
    """``make()``, which reads the record ``path`` and returns what keeps it, under the
    record's lock (``RecordLock``: ``in_place``, ``hint``), then held as long as what it
    returned lives."""
    lock = RecordLock(path, what, in_place=in_place, hint=hint)
    try:
        owner = make()
    except BaseException:
        lock.release()
        raise
    lock.bind(owner)
    return owner


def _flock(fd: int) -> bool:
    """Lock ``fd`` exclusively without waiting (False: another holder has it). POSIX: the
    records' folders, modes and locks are (``write_atomic`` sets modes with ``fchmod`` too)."""
    import fcntl  # here: importing this module needs no POSIX

    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True
