"""One keeper per NV record (review rv3, F2): a node's or gateway's NV file kept by one process
is refused by a second, the C node, the C gateway and the emulator alike, before a bus opens.

Two processes on one record both spend what it holds (rv3: two emulators on one file holding
1 J spent 2 J). The keeper here is another process holding the file's ``flock`` as each of
them does while it runs (the C ports and the emulator lock the NV file itself, so they exclude
each other); once it lets go, the same start gets past its NV checks.
"""

from __future__ import annotations

import subprocess
import sys
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from support.firmware_build import built
from support.procs import wait

_HOLD = (
    "import fcntl, os, sys, time\n"
    "fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT, 0o600)\n"
    "fcntl.flock(fd, fcntl.LOCK_EX)\n"
    "print('kept', flush=True)\n"
    "time.sleep(120)\n"
)


@contextmanager
def _kept(path: Path) -> Iterator[None]:
    """Another process keeps ``path`` (as a running node does) until the block ends."""
    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLD, str(path)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "kept"
        yield
    finally:
        holder.kill()
        holder.wait(30)


def _run(argv: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(argv, capture_output=True, text=True, timeout=60, cwd=cwd)


def _refused(run: subprocess.CompletedProcess[str], words: str) -> None:
    assert run.returncode == 2, run.stderr
    assert run.stderr.count("\n") == 1 and words in run.stderr, run.stderr


def _bus_refused(run: subprocess.CompletedProcess[str]) -> None:
    """Past the NV checks: stopped by the CAN interface that does not exist."""
    assert run.returncode == 2 and "kept by another holder" not in run.stderr, run.stderr
    assert "nosuchcan" in run.stderr or "CAN socket" in run.stderr, run.stderr


def test_the_c_node_refuses_an_nv_file_another_process_keeps(tmp_path: Path) -> None:
    node = [str(built("build/canergy-node")), "--node", "1", "-i", "socketcan"]
    argv = [*node, "-c", "nosuchcan0", "--nv", "n.nv"]
    (tmp_path / "n.nv").write_bytes(b"")
    with _kept(tmp_path / "n.nv"):
        _refused(_run(argv, tmp_path), "canergy-node: error: --nv n.nv is kept by another holder")
    _bus_refused(_run(argv, tmp_path))


def test_the_c_gateway_refuses_an_nv_file_another_process_keeps(tmp_path: Path) -> None:
    gateway = [str(built("build/canergy-gateway")), "--node", "1", "--nodes", "2"]
    argv = [*gateway, "-c", "nosuchcan0", "--upstream-channel", "nosuchcan1", "--nv", "g.nv"]
    (tmp_path / "g.nv").write_bytes(b"")
    with _kept(tmp_path / "g.nv"):
        _refused(_run(argv, tmp_path), "--nv g.nv is kept by another holder")
    _bus_refused(_run(argv, tmp_path))


def test_the_emulator_refuses_an_nv_file_another_process_keeps(tmp_path: Path) -> None:
    bus = ["-i", "virtual", "-c", f"keepers-{uuid.uuid4().hex}"]
    argv = [sys.executable, "-m", "firmware_model", "--node", "1", *bus, "--nv", "n.nv"]
    with _kept(tmp_path / "n.nv"):
        _refused(_run(argv, tmp_path), "NV record n.nv is kept by another holder")
    started = subprocess.Popen([*argv, "--status-file", "st.json"], cwd=tmp_path)
    try:  # free again: it runs, its record taken, and reports
        wait(lambda: (tmp_path / "st.json").exists() or started.poll() is not None, "a status")
        assert started.poll() is None and (tmp_path / "st.json").exists()
    finally:
        started.kill()
        started.wait(30)
