"""Key files and per-node keys. A key is never logged, printed or put in an error message.

The supervisor holds the **master key**; each node holds only its own **node key**, derived from
the master by NIST SP 800-108 in counter mode with AES-CMAC (``cryptography``'s ``KBKDFCMAC``;
the C client's ``canergy_kdf_cmac_ctr`` gives the same bytes), label ``canergy node key``,
context = node id (1 byte) || epoch (4 bytes, big-endian). A compromised node cannot forge for
another. The **epoch** is the provisioning generation: a supervisor whose books start again (a
new state file, counters back at zero) needs keys of a new epoch, or frames of the old life would
verify again.

A key file is text, mode 0600 (anything more open is refused)::

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
        mode = path.stat().st_mode
        text = path.read_text(encoding="ascii")
    except (OSError, UnicodeDecodeError) as exc:
        raise KeyFileError(f"{path}: cannot read the key file ({exc.__class__.__name__})") from None
    if not stat.S_ISREG(mode):
        raise KeyFileError(f"{path}: not a regular file")
    if mode & 0o077:
        raise KeyFileError(
            f"{path}: mode {stat.S_IMODE(mode):04o} lets others read it; chmod 600 {path}"
        )
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
