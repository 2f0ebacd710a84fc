"""Files that survive ``kill -9`` and power loss: write a temporary, fsync, rename, fsync the
directory. A reader sees the old content or the new, never a mix."""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path
from typing import Any


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
