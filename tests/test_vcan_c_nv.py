"""The C programs' NV files (canergy-node, canergy-gateway) on a real filesystem, traced with
strace: a new (empty) file has its directory fsynced before the program goes on (without that,
a power loss soon after the first record was fsynced could lose the file's name, and the record
with it); a file holding a record is opened as it is."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest
from support.firmware_build import built
from support.firmware_build import c_node as c_node  # the fixture: makes canergy-node
from support.vcan import IFACE
from support.vcan import vcan_up as vcan_up  # the fixture: fails when vcan0 is missing

pytestmark = pytest.mark.vcan


def _traced(argv: list[str], log: Path) -> str:
    """Run ``argv`` for a few seconds under strace (``timeout`` stops it with SIGTERM, as an
    operator would) and return the trace of its opens and fsyncs."""
    assert shutil.which("strace"), "strace is missing: apt install strace"
    trace = ["strace", "-f", "-qq", "-e", "trace=openat,fsync,unlink", "-o", str(log)]
    run = subprocess.run(
        [*trace, "timeout", "-s", "TERM", "5", *argv], capture_output=True, text=True, timeout=120
    )
    assert run.returncode in (0, 124), run.stderr  # 124: stopped by timeout
    return log.read_text()


def _opens(trace: str, path: Path) -> list[tuple[str, str, int]]:
    """Each ``openat`` of ``path`` in ``trace``: its flags, its result and where it ends."""
    pattern = rf'openat\(AT_FDCWD, "{re.escape(str(path))}", ([A-Z_|]+)[^)]*\)\s+= (-?\d+)'
    return [(m.group(1), m.group(2), m.end()) for m in re.finditer(pattern, trace)]


def _check(first: str, again: str, nv: Path, held_a_record: bool) -> None:
    opened = [o for o in _opens(first, nv) if "O_CREAT" in o[0].split("|")]
    assert opened and opened[0][1] != "-1", first
    after = first[opened[0][2] :]
    folder = [o for o in _opens(after, nv.parent) if "O_DIRECTORY" in o[0].split("|")]
    assert folder and folder[0][1] != "-1", after
    assert re.search(rf"fsync\({folder[0][1]}\)\s+= 0", after[folder[0][2] :]), after
    # started again: a file holding a record is opened as it is; one still empty (a node that
    # was never admitted writes none) has its directory synced again
    synced = [o for o in _opens(again, nv.parent) if "O_DIRECTORY" in o[0]]
    assert _opens(again, nv) and bool(synced) is not held_a_record, again


def test_the_c_node_syncs_the_directory_of_a_new_nv_file(tmp_path: Path, c_node: Path) -> None:
    nv = tmp_path / "n9.nv"
    argv = [str(c_node), "--node", "9", "-i", "socketcan", "-c", IFACE, "--nv", str(nv)]
    first = _traced(argv, tmp_path / "first.log")
    held_a_record = nv.stat().st_size > 0
    again = _traced(argv, tmp_path / "again.log")
    _check(first, again, nv, held_a_record)


def test_the_c_gateway_syncs_the_directory_of_a_new_nv_file(tmp_path: Path) -> None:
    gateway = built("build/canergy-gateway")
    nv = tmp_path / "gw.nv"
    argv = [str(gateway), "--node", "30", "--nodes", "1", "-i", "socketcan", "-c", "vcan1"]
    argv += ["--upstream-channel", IFACE, "--nv", str(nv)]
    first = _traced(argv, tmp_path / "first.log")
    held_a_record = nv.stat().st_size > 0
    again = _traced(argv, tmp_path / "again.log")
    _check(first, again, nv, held_a_record)
