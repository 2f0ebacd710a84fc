"""The key that seals a state file, and the record of the keys that already began books.

In authenticated mode a state file carries ``mac``: AES-128-CMAC (all 16 bytes) over its canonical
content, under a **state key** derived from the master key by the project's KDF (SP 800-108
counter mode with CMAC, as node keys): label ``canergy state key``, context = epoch (4 bytes,
big-endian), and for a gateway its node id (1 byte) after it. Nobody without the master key can
write a file that passes.

A key may keep one life of books: new books (a state file started again) under keys that kept
others let frames of the old life verify again. ``claim`` keeps the **epochs record** beside the
key file (``master.key.epochs``, mode 0600): one line per state key that began books, and it
refuses to begin new books under a key already listed there.
"""

from __future__ import annotations

import functools
import hmac
import os
from collections.abc import Callable
from pathlib import Path

from cryptography.hazmat.primitives import cmac
from cryptography.hazmat.primitives.ciphers import algorithms
from cryptography.hazmat.primitives.kdf.kbkdf import KBKDFCMAC, CounterLocation, Mode

from canergy.auth.keys import KEY_BYTES, Key

LABEL = b"canergy state key"
MAC_PREFIX = "cmac:"
RECORD_SUFFIX = ".epochs"
_TAG = b"canergy epochs record"
"""What a state key MACs to name itself in the epochs record (the key stays secret)."""


class StateKeyError(ValueError):
    """Keys that may not keep these books; the message names files, never a key."""


def derive(master: bytes, label: bytes, context: bytes) -> bytes:
    """The project's KDF: SP 800-108 counter mode with AES-CMAC, 32-bit counter and length."""
    kdf = KBKDFCMAC(
        algorithms.AES,
        Mode.CounterMode,
        KEY_BYTES,
        4,
        4,
        CounterLocation.BeforeFixed,
        label,
        context,
        None,
    )
    return kdf.derive(master)


class StateSeal:
    """MACs a state file's canonical content under one state key."""

    __slots__ = ("_keyed", "epoch", "identity")

    def __init__(self, secret: bytes, epoch: int, identity: int | None = None) -> None:
        self._keyed = cmac.CMAC(algorithms.AES(secret))  # each MAC starts from a copy
        self.epoch = epoch
        self.identity = identity
        """A gateway's node id; None for a supervisor."""

    def __repr__(self) -> str:  # never show the key
        return f"StateSeal(epoch={self.epoch}, identity={self.identity})"

    def mac(self, content: bytes) -> str:
        """``cmac:<32 hex digits>``."""
        c = self._keyed.copy()
        c.update(content)
        return MAC_PREFIX + c.finalize().hex()

    def matches(self, content: bytes, found: object) -> bool:
        """``found`` is this content's MAC (compared in constant time)."""
        return (
            isinstance(found, str)
            and found.isascii()
            and hmac.compare_digest(found, self.mac(content))
        )

    def tag(self) -> str:
        """Names this key in the epochs record: 16 hex digits, which reveal nothing of it."""
        return self.mac(_TAG).removeprefix(MAC_PREFIX)[:16]


def state_seal(key: Key, identity: int | None = None) -> StateSeal:
    """The seal of the books kept under ``key`` (a gateway: ``identity``, its node id)."""
    context = key.epoch.to_bytes(4, "big") + (b"" if identity is None else bytes([identity]))
    return StateSeal(derive(key.secret, LABEL, context), key.epoch, identity)


def epochs_record(key_path: Path) -> Path:
    return key_path.with_name(key_path.name + RECORD_SUFFIX)


def claim(key_path: Path, seal: StateSeal, books: Path, *, fresh: bool) -> Callable[[], None]:
    """Check now that ``seal``'s key may keep ``books`` (``fresh``, no state file: new books,
    refused under a key the record lists), and return what records it, to call before the
    books' first save (a run that stops before it, on a bus that will not open, claims
    nothing)."""
    record = epochs_record(key_path)
    text = _read(record)
    tag = seal.tag()
    kept = _listed(text).get(tag)
    if kept is not None and fresh:
        raise StateKeyError(
            f"{books} does not exist, and the keys of {key_path} (epoch {seal.epoch}) already "
            f"began books ({kept}, says {record}): new books under them would let frames of "
            "the old ones verify again. Put back that state file as it was last saved (an "
            "older copy does the same harm), or begin the new books with keys of a new epoch "
            "(canergy keys --epoch N, and new node keys)"
        )
    if kept is not None:
        return lambda: None
    _check_writable(record)
    torn = "\n" if text and not text.endswith("\n") else ""
    line = f"{torn}{tag} epoch={seal.epoch} state={books.absolute()}\n"
    return functools.partial(_append, record, line)


def _read(record: Path) -> str:
    if record.exists() and not record.is_file():  # a FIFO would block the start
        raise StateKeyError(f"{record}: the epochs record is not a regular file")
    try:
        return record.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        return ""
    except OSError as exc:
        raise StateKeyError(f"{record}: cannot read the epochs record ({exc})") from None


def _listed(text: str) -> dict[str, str]:
    """The record's lines by tag (a torn line is ignored)."""
    lines = (line.split(" ", 1) for line in text.splitlines())
    return {parts[0]: parts[1] for parts in lines if len(parts) == 2 and len(parts[0]) == 16}


def _check_writable(record: Path) -> None:
    target = record if record.exists() else record.parent
    if not os.access(target, os.W_OK):
        raise StateKeyError(
            f"{record}: cannot write the epochs record (it lists the keys that began books, "
            "beside the key file): make its directory writable, or create it writable (mode 0600)"
        )


def _append(record: Path, line: str) -> None:
    """Add ``line`` to the record (created 0600 whatever the umask) and sync it and its folder."""
    try:
        fd = os.open(record, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW, 0o600)
        try:
            os.fchmod(fd, 0o600)
            os.write(fd, line.encode())
            os.fsync(fd)
        finally:
            os.close(fd)
        _sync_folder(record.parent)
    except OSError as exc:
        raise StateKeyError(f"{record}: cannot write the epochs record ({exc.strerror})") from None


def _sync_folder(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
