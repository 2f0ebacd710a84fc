"""Key files and per-node keys. A key is never logged, printed or put in an error message.

The supervisor holds the **master key**; each node holds only its own **node key**, derived from
the master by NIST SP 800-108 in counter mode with AES-CMAC (``cryptography``'s ``KBKDFCMAC``;
the C client's ``canergy_kdf_cmac_ctr`` gives the same bytes), label ``canergy node key``,
context = node id (1 byte) || epoch (4 bytes, big-endian). A compromised node cannot forge for
another. The **epoch** is the provisioning generation: a supervisor whose books start again (a
new state file, counters back at zero) needs keys of a new epoch, or frames of the old life would
verify again.

A key file is text, mode 0600 (anything more open is refused), a regular file of at most
``KEY_FILE_MAX`` bytes (a FIFO, a device or a huge file is refused before anything is read)::

    # canergy key: keep it secret
    kind=node
    node=3
    epoch=1
    key=<32 hex digits>
"""

from __future__ import annotations

import functools
import os
import secrets
import stat
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from cryptography.hazmat.primitives.ciphers import algorithms
from cryptography.hazmat.primitives.kdf.kbkdf import KBKDFCMAC, CounterLocation, Mode

from canergy.messages import MAX_NODE, MIN_NODE

KEY_BYTES = 16
LABEL = b"canergy node key"
EPOCH_MAX = 0xFFFF_FFFF
KEY_FILE_MAX = 4096
"""A key file's size limit in bytes (the C node's too): ``write_key`` writes about 100."""
_KINDS = {
    stat.S_IFIFO: "a FIFO",
    stat.S_IFCHR: "a character device",
    stat.S_IFBLK: "a block device",
    stat.S_IFDIR: "a directory",
    stat.S_IFSOCK: "a socket",
}


class KeyFileError(ValueError):
    """A key file that cannot be used; the message names the file, never the key."""


@dataclass(frozen=True, slots=True)
class Key:
    kind: str
    """``master`` or ``node``."""
    epoch: int
    secret: bytes
    node: int | None = None

    def __repr__(self) -> str:  # never show the secret
        return f"Key(kind={self.kind!r}, node={self.node}, epoch={self.epoch})"

    def node_key(self, node: int) -> bytes:
        """This node's key: derived from a master key, or this node key itself."""
        if self.kind == "node":
            if node != self.node:
                raise KeyFileError(f"a key for node {self.node} cannot serve node {node}")
            return self.secret
        return derive_node_key(self.secret, node, self.epoch)


def derive_node_key(master: bytes, node: int, epoch: int) -> bytes:
    context = bytes([node]) + epoch.to_bytes(4, "big")
    kdf = KBKDFCMAC(
        algorithms.AES,
        Mode.CounterMode,
        KEY_BYTES,
        4,
        4,
        CounterLocation.BeforeFixed,
        LABEL,
        context,
        None,
    )
    return kdf.derive(master)


def load_key(path: Path) -> Key:
    """Read and check a key file (mode 0600 or stricter, every field valid)."""
    try:
        text = _read_key_file(path).decode("ascii")
    except UnicodeDecodeError as exc:
        raise KeyFileError(f"{path}: cannot read the key file ({exc.__class__.__name__})") from None
    fields: dict[str, str] = {}
    for number, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        name, sep, value = line.partition("=")
        if not sep or name.strip() in fields:
            raise KeyFileError(f"{path}:{number}: expected one name=value per line")
        fields[name.strip()] = value.strip()
    return _key(path, fields)


def _read_key_file(path: Path) -> bytes:
    """The bytes of a key file that passes ``_check_file``: checked before it is opened (a
    device is never opened), then again on the opened file (it may have been replaced), opened
    with O_NONBLOCK (a FIFO put there meanwhile cannot block) and read to exactly its size."""
    try:
        _check_file(path, os.stat(path))
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
        try:
            size = _check_file(path, os.fstat(fd))
            data = _read_at_most(fd, size + 1)  # one byte more: a file that grew shows it
        finally:
            os.close(fd)
    except OSError as exc:
        raise KeyFileError(f"{path}: cannot read the key file ({exc.__class__.__name__})") from None
    if len(data) != size:
        raise KeyFileError(f"{path}: changed while read ({size} bytes by its size, {len(data)})")
    return data


def _read_at_most(fd: int, limit: int) -> bytes:
    data = b""
    while len(data) < limit and (chunk := os.read(fd, limit - len(data))):
        data += chunk
    return data


def _check_file(path: Path, st: os.stat_result) -> int:
    """The size of a key file: a regular file, mode 0600 or stricter, at most KEY_FILE_MAX."""
    if not stat.S_ISREG(st.st_mode):
        kind = _KINDS.get(stat.S_IFMT(st.st_mode), "of an unknown type")
        raise KeyFileError(f"{path}: not a regular file ({kind})")
    if st.st_mode & 0o077:
        raise KeyFileError(
            f"{path}: mode {stat.S_IMODE(st.st_mode):04o} lets others read it; chmod 600 {path}"
        )
    if st.st_size > KEY_FILE_MAX:
        raise KeyFileError(
            f"{path}: {st.st_size} bytes, more than a key file holds ({KEY_FILE_MAX})"
        )
    return st.st_size


def _key(path: Path, fields: dict[str, str]) -> Key:
    kind = fields.get("kind")
    if kind not in ("master", "node"):
        raise KeyFileError(f"{path}: kind must be master or node")
    wanted = {"kind", "epoch", "key"} | ({"node"} if kind == "node" else set())
    if set(fields) != wanted:
        raise KeyFileError(f"{path}: a {kind} key file holds exactly {', '.join(sorted(wanted))}")
    try:
        secret = bytes.fromhex(fields["key"])
        epoch = int(fields["epoch"])
        node = int(fields["node"]) if kind == "node" else None
    except ValueError:
        raise KeyFileError(f"{path}: key must be hex, epoch and node integers") from None
    if len(secret) != KEY_BYTES:
        raise KeyFileError(f"{path}: key must be {KEY_BYTES} bytes ({2 * KEY_BYTES} hex digits)")
    if not 0 <= epoch <= EPOCH_MAX:
        raise KeyFileError(f"{path}: epoch must be 0 to {EPOCH_MAX}")
    if node is not None and not MIN_NODE <= node <= MAX_NODE:
        raise KeyFileError(f"{path}: node must be {MIN_NODE} to {MAX_NODE}")
    return Key(kind, epoch, secret, node)


def write_key(path: Path, key: Key) -> None:
    """Create ``path`` (never replace one) with mode 0600."""
    lines = ["# canergy key: keep it secret (mode 0600)", f"kind={key.kind}"]
    if key.node is not None:
        lines.append(f"node={key.node}")
    lines += [f"epoch={key.epoch}", f"key={key.secret.hex()}", ""]
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        raise KeyFileError(f"{path} exists: key files are never replaced") from None
    with os.fdopen(fd, "w", encoding="ascii") as f:
        f.write("\n".join(lines))


def frame_auth_keys(key: Key) -> Callable[[int], bytes]:
    """Node keys on demand, each derived once."""
    return functools.cache(key.node_key)


def new_master(epoch: int) -> Key:
    return Key("master", epoch, secrets.token_bytes(KEY_BYTES))


def node_key_of(master: Key, node: int) -> Key:
    return Key("node", master.epoch, master.node_key(node), node)
