"""The C node (firmware/build/canergy-node) and its local files (security second pass, items 11
and 12): a key file must be a regular file of a bounded size, read without blocking (a FIFO,
``/dev/zero`` or a huge file is refused at once, as in Python), and ``--nv`` and
``--status-file`` must not name one file, through symlinks and hard links too (the status JSON
would replace the NV record). Everything here is refused before the bus is opened: no vcan0.
"""

from __future__ import annotations

import os
import subprocess
from collections.abc import Callable
from pathlib import Path

import pytest

from canergy.auth.keys import KEY_FILE_MAX, new_master, node_key_of, write_key

FIRMWARE = Path(__file__).resolve().parents[1] / "firmware"
C_NODE = FIRMWARE / "build" / "canergy-node"


@pytest.fixture(scope="module")
def c_node() -> Path:
    """The binary, rebuilt when its sources changed (make); a failed build fails loudly."""
    build = subprocess.run(
        ["make", "-s", "-C", str(FIRMWARE), "build/canergy-node"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert build.returncode == 0, f"make canergy-node failed:\n{build.stdout}{build.stderr}"
    return C_NODE


def _run(c_node: Path, tmp: Path, *args: str) -> subprocess.CompletedProcess[str]:
    argv = [str(c_node), "--node", "1", "-i", "socketcan", "-c", "nosuchcan0", *args]
    return subprocess.run(argv, capture_output=True, text=True, timeout=10, cwd=tmp)


def _refused(run: subprocess.CompletedProcess[str], words: str) -> None:
    assert run.returncode == 2, run.stderr
    assert run.stderr.count("\n") == 1 and words in run.stderr, run.stderr


# --- item 11: key files -----------------------------------------------------------------------


def _node_key(path: Path, pad_to: int = 0) -> Path:
    write_key(path, node_key_of(new_master(1), 1))
    with open(path, "a", encoding="ascii") as f:  # comment bytes up to pad_to
        f.write("#" * max(0, pad_to - path.stat().st_size))
    return path


def _fifo(tmp: Path) -> Path:
    os.mkfifo(tmp / "fifo.key", 0o600)
    return tmp / "fifo.key"


def _directory(tmp: Path) -> Path:
    (tmp / "dir.key").mkdir(mode=0o700)
    return tmp / "dir.key"


BAD_KEYS: dict[str, tuple[Callable[[Path], Path], str]] = {
    "fifo": (_fifo, "not a regular file (a FIFO)"),
    "/dev/zero": (lambda tmp: Path("/dev/zero"), "not a regular file (a character device)"),
    "oversize": (
        lambda tmp: _node_key(tmp / "big.key", KEY_FILE_MAX + 1),
        f"{KEY_FILE_MAX + 1} bytes, more than a key file holds ({KEY_FILE_MAX})",
    ),
    "directory": (_directory, "not a regular file (a directory)"),
}


@pytest.mark.parametrize("kind", BAD_KEYS)
def test_the_c_node_refuses_a_key_file_that_is_not_a_small_regular_file(
    kind: str, c_node: Path, tmp_path: Path
) -> None:
    make, words = BAD_KEYS[kind]
    key = make(tmp_path)
    run = _run(c_node, tmp_path, "--nv", "n.nv", "--auth", str(key))
    _refused(run, f"canergy-node: error: --auth {key}: {words}")
    assert not (tmp_path / "n.nv").exists()


def test_the_c_node_still_reads_a_key_file_of_the_largest_size(
    c_node: Path, tmp_path: Path
) -> None:
    """Past the key checks (the bus, which does not exist here, is what stops it)."""
    key = _node_key(tmp_path / "n1.key", KEY_FILE_MAX)
    assert key.stat().st_size == KEY_FILE_MAX
    run = _run(c_node, tmp_path, "--nv", "n.nv", "--auth", str(key))
    assert run.returncode == 2 and "--auth" not in run.stderr, run.stderr
    key.chmod(0o640)
    _refused(_run(c_node, tmp_path, "--nv", "n.nv", "--auth", str(key)), "chmod 600")


# --- item 12: --nv and --status-file ----------------------------------------------------------


def _same_by_symlink(tmp: Path) -> tuple[str, str]:
    (tmp / "n.nv").write_bytes(b"")
    (tmp / "status.json").symlink_to("n.nv")
    return "n.nv", "status.json"


def _same_by_dangling_symlink(tmp: Path) -> tuple[str, str]:
    (tmp / "status.json").symlink_to("n.nv")  # the NV file does not exist yet
    return "n.nv", "status.json"


def _same_by_hard_link(tmp: Path) -> tuple[str, str]:
    (tmp / "n.nv").write_bytes(b"")
    os.link(tmp / "n.nv", tmp / "status.json")
    return "n.nv", "status.json"


def _same_by_spelling(tmp: Path) -> tuple[str, str]:
    (tmp / "sub").mkdir()
    return "sub/n.nv", str(tmp / "sub" / ".." / "sub" / "n.nv")  # neither exists


def _same_through_a_linked_directory(tmp: Path) -> tuple[str, str]:
    (tmp / "real").mkdir()
    (tmp / "alias").symlink_to("real")
    return "real/n.nv", "alias/n.nv"


SAME = [
    _same_by_symlink,
    _same_by_dangling_symlink,
    _same_by_hard_link,
    _same_by_spelling,
    _same_through_a_linked_directory,
]


@pytest.mark.parametrize("same", SAME, ids=lambda f: f.__name__[1:])
def test_the_c_node_refuses_nv_and_status_file_naming_one_file(
    same: Callable[[Path], tuple[str, str]], c_node: Path, tmp_path: Path
) -> None:
    nv, status = same(tmp_path)
    before = sorted(p.name for p in tmp_path.rglob("*"))
    run = _run(c_node, tmp_path, "--nv", nv, "--status-file", status)
    _refused(run, f"--nv {nv} and --status-file {status} name the same file")
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing created


def test_the_c_node_accepts_two_files_that_only_look_alike(c_node: Path, tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    (tmp_path / "a" / "n.nv").write_bytes(b"")
    (tmp_path / "b" / "n.nv").write_bytes(b"")  # same name, another directory
    (tmp_path / "dangling").symlink_to("elsewhere.json")
    for nv, status in (("a/n.nv", "b/n.nv"), ("n.nv", "dangling"), ("a/n.nv", "a/new.json")):
        run = _run(c_node, tmp_path, "--nv", nv, "--status-file", status)
        assert run.returncode == 2 and "same file" not in run.stderr, run.stderr  # the bus
