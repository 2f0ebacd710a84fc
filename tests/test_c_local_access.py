"""The C node and gateway (firmware/build/canergy-node, canergy-gateway) and their local files
(security second pass, items 11 and 12; issue 40 item 8): a key file must be a regular file of a
bounded size, read without blocking (a FIFO, ``/dev/zero`` or a huge file is refused at once, as
in Python), and no two file flags (``--nv``, ``--status-file``, the node's ``--auth``) may name
one file, through symlinks and hard links too (the status JSON would replace the NV record or
the key); no folder of the NV record's or a key file's, nor a key file's mode, may let others
replace or read it, refused as Python refuses it, in its words (issue 40). Everything here is
refused before the bus is opened: no vcan0.
"""

from __future__ import annotations

import os
import subprocess
from collections.abc import Callable
from pathlib import Path

import pytest
from support.firmware_build import built, refused, run_without_bus
from support.firmware_build import c_gateway as c_gateway  # the fixtures
from support.firmware_build import c_node as c_node

from canergy.auth.keys import (
    KEY_FILE_MAX,
    KeyFileError,
    load_key,
    new_master,
    node_key_of,
    write_key,
)
from canergy.live.atomic import check_private_dir

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
    run = run_without_bus(c_node, tmp_path, "--nv", "n.nv", "--auth", str(key))
    refused(run, f"canergy-node: error: --auth {key}: {words}")
    assert not (tmp_path / "n.nv").exists()


def test_the_c_node_still_reads_a_key_file_of_the_largest_size(
    c_node: Path, tmp_path: Path
) -> None:
    """Past the key checks (the bus, which does not exist here, is what stops it)."""
    key = _node_key(tmp_path / "n1.key", KEY_FILE_MAX)
    assert key.stat().st_size == KEY_FILE_MAX
    run = run_without_bus(c_node, tmp_path, "--nv", "n.nv", "--auth", str(key))
    assert run.returncode == 2 and "--auth" not in run.stderr, run.stderr
    key.chmod(0o640)
    refused(run_without_bus(c_node, tmp_path, "--nv", "n.nv", "--auth", str(key)), "chmod 600")


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


@pytest.mark.parametrize("program", ["canergy-node", "canergy-gateway"])
@pytest.mark.parametrize("same", SAME, ids=lambda f: f.__name__[1:])
def test_the_c_programs_refuse_nv_and_status_file_naming_one_file(
    same: Callable[[Path], tuple[str, str]], program: str, tmp_path: Path
) -> None:
    binary = built(f"build/{program}")
    nv, status = same(tmp_path)
    before = sorted(p.name for p in tmp_path.rglob("*"))
    run = run_without_bus(binary, tmp_path, "--nv", nv, "--status-file", status)
    refused(run, f"{program}: error: --nv {nv} and --status-file {status} name the same file")
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing created


@pytest.mark.parametrize("program", ["canergy-node", "canergy-gateway"])
def test_the_c_programs_accept_two_files_that_only_look_alike(program: str, tmp_path: Path) -> None:
    binary = built(f"build/{program}")
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    (tmp_path / "a" / "n.nv").write_bytes(b"")
    (tmp_path / "b" / "n.nv").write_bytes(b"")  # same name, another directory
    (tmp_path / "dangling").symlink_to("elsewhere.json")
    for nv, status in (("a/n.nv", "b/n.nv"), ("n.nv", "dangling"), ("a/n.nv", "a/new.json")):
        run = run_without_bus(binary, tmp_path, "--nv", nv, "--status-file", status)
        assert run.returncode == 2 and "same file" not in run.stderr, run.stderr  # the bus


def test_the_c_node_refuses_its_key_file_named_as_its_nv_or_status_file(
    c_node: Path, tmp_path: Path
) -> None:
    """The key is read at start, the NV record and the status written over it afterwards: the
    key would be gone at the next start."""
    key = _node_key(tmp_path / "n1.key")
    (tmp_path / "alias.key").symlink_to("n1.key")
    os.link(key, tmp_path / "hard.key")
    refused(
        run_without_bus(c_node, tmp_path, "--nv", "alias.key", "--auth", str(key)),
        f"--nv alias.key and --auth {key} name the same file",
    )
    refused(
        run_without_bus(
            c_node, tmp_path, "--nv", "n.nv", "--status-file", "hard.key", "--auth", "n1.key"
        ),
        "--status-file hard.key and --auth n1.key name the same file",
    )
    assert key.read_text() == (tmp_path / "hard.key").read_text()
    assert not (tmp_path / "n.nv").exists()


# --- the C gateway's --upstream-auth: the node's key file checks, under its own flag ---------


@pytest.mark.parametrize("kind", BAD_KEYS)
def test_the_c_gateway_refuses_an_upstream_key_file_that_is_not_a_small_regular_file(
    kind: str, c_gateway: Path, tmp_path: Path
) -> None:
    make, words = BAD_KEYS[kind]
    key = make(tmp_path)
    run = run_without_bus(c_gateway, tmp_path, "--nv", "g.nv", "--upstream-auth", str(key))
    refused(run, f"canergy-gateway: error: --upstream-auth {key}: {words}")
    assert not (tmp_path / "g.nv").exists()


def test_the_c_gateway_takes_only_its_own_node_key_above(c_gateway: Path, tmp_path: Path) -> None:
    """Node 1 above: the key of node 1, not another node's nor the master key; a good one gets
    past the key checks (the bus, which does not exist here, is what stops it); the FD layout
    only with a key; the key file is no NV or status file."""
    master = new_master(1)
    write_key(tmp_path / "root.key", master)
    write_key(tmp_path / "n2.key", node_key_of(master, 2))
    for name, words in (
        ("root.key", "a node takes its own node key, not the master key"),
        ("n2.key", "a key for node 2 cannot serve node 1"),
    ):
        run = run_without_bus(c_gateway, tmp_path, "--nv", "g.nv", "--upstream-auth", name)
        refused(run, f"canergy-gateway: error: --upstream-auth {name}: {words}")
    key = _node_key(tmp_path / "n1.key")
    for layout in ((), ("--upstream-fd",)):
        run = run_without_bus(
            c_gateway, tmp_path, "--nv", "g.nv", "--upstream-auth", str(key), *layout
        )
        assert run.returncode == 2 and "--upstream-auth" not in run.stderr, run.stderr
        assert "CAN socket" in run.stderr  # past every check: the bus is what stops it
    refused(
        run_without_bus(c_gateway, tmp_path, "--nv", "g.nv", "--upstream-fd"),
        "argument --upstream-fd: only with --upstream-auth",
    )
    refused(
        run_without_bus(c_gateway, tmp_path, "--nv", "n1.key", "--upstream-auth", "n1.key"),
        "--nv n1.key and --upstream-auth n1.key name the same file",
    )
    assert not (tmp_path / "g.nv").exists()


# --- the C gateway's --auth: a master key of its own below, the same file checks ---------------


@pytest.mark.parametrize("kind", BAD_KEYS)
def test_the_c_gateway_refuses_a_master_key_file_below_that_is_not_a_small_regular_file(
    kind: str, c_gateway: Path, tmp_path: Path
) -> None:
    make, words = BAD_KEYS[kind]
    key = make(tmp_path)
    run = run_without_bus(c_gateway, tmp_path, "--nv", "g.nv", "--auth", str(key))
    refused(run, f"canergy-gateway: error: --auth {key}: {words}")
    assert not (tmp_path / "g.nv").exists()


def test_the_c_gateway_takes_a_master_key_of_its_own_below(c_gateway: Path, tmp_path: Path) -> None:
    """Below: a master key, not a node key, and not the root's master key the key above was
    derived from; a good one, with either layout on either leg, gets past the key checks; --fd
    only with a key; the key file is no NV file; a loose mode is refused."""
    root, own = new_master(1), new_master(1)
    write_key(tmp_path / "root.key", root)
    write_key(tmp_path / "own.key", own)
    write_key(tmp_path / "n1.key", node_key_of(root, 1))
    write_key(tmp_path / "g2.key", node_key_of(own, 2))
    refused(
        run_without_bus(c_gateway, tmp_path, "--nv", "g.nv", "--auth", "g2.key"),
        "canergy-gateway: error: --auth g2.key: a node key; downstream the gateway is a "
        "supervisor and needs a master key of its own",
    )
    refused(
        run_without_bus(
            c_gateway, tmp_path, "--nv", "g.nv", "--auth", "root.key", "--upstream-auth", "n1.key"
        ),
        "canergy-gateway: error: --auth root.key: the master key --upstream-auth n1.key was "
        "derived from",
    )
    for layout in ((), ("--fd",), ("--fd", "--upstream-fd")):
        run = run_without_bus(
            c_gateway,
            tmp_path,
            "--nv",
            "g.nv",
            "--auth",
            "own.key",
            "--upstream-auth",
            "n1.key",
            *layout,
        )
        assert run.returncode == 2 and "CAN socket" in run.stderr, run.stderr  # past every check
    refused(
        run_without_bus(c_gateway, tmp_path, "--nv", "g.nv", "--fd"),
        "argument --fd: only with --auth",
    )
    refused(
        run_without_bus(c_gateway, tmp_path, "--nv", "own.key", "--auth", "own.key"),
        "--nv own.key and --auth own.key name the same file",
    )
    (tmp_path / "own.key").chmod(0o640)
    run = run_without_bus(c_gateway, tmp_path, "--nv", "g.nv", "--auth", "own.key")
    refused(run, "canergy-gateway: error: --auth own.key: mode 0640 lets others read it")
    assert not (tmp_path / "g.nv").exists()


# --- the --nv folder: no one else may replace or roll back the record -------------------------


def _world_writable(tmp: Path) -> str:
    (tmp / "d").mkdir(mode=0o700)
    (tmp / "d").chmod(0o777)
    return "d/n.nv"


def _group_writable(tmp: Path) -> str:
    (tmp / "d").mkdir(mode=0o700)
    (tmp / "d").chmod(0o770)
    return str(tmp / "d" / "n.nv")


def _writable_above(tmp: Path) -> str:
    (tmp / "open").mkdir(mode=0o700)
    (tmp / "open").chmod(0o777)
    (tmp / "open" / "d").mkdir(mode=0o700)
    return str(tmp / "open" / "d" / "n.nv")


def _writable_above_the_link_target(tmp: Path) -> str:
    """The folder is private as written (a link in a private folder to a private folder), but
    the link's target lies in a folder others may write: found once the link is resolved."""
    _writable_above(tmp)
    (tmp / "link").symlink_to(tmp / "open" / "d")
    return "link/n.nv"


def _writable_through_dot_dot(tmp: Path) -> str:
    _world_writable(tmp)
    return "nosuchdir/../d/n.nv"  # lexically tmp/d, as os.path.abspath makes it


OPEN_FOLDERS = [
    _world_writable,
    _group_writable,
    _writable_above,
    _writable_above_the_link_target,
    _writable_through_dot_dot,
]


def _python_refusal(nv: str, tmp: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    """What ``check_private_dir`` says of ``nv`` (relative to ``tmp``): the C line's text."""
    monkeypatch.chdir(tmp)
    with pytest.raises(PermissionError) as refused:
        check_private_dir(Path(nv), "--nv")
    return str(refused.value)


@pytest.mark.parametrize("program", ["canergy-node", "canergy-gateway"])
@pytest.mark.parametrize("folder", OPEN_FOLDERS, ids=lambda f: f.__name__[1:])
def test_the_c_programs_refuse_an_nv_folder_others_may_write_as_python_does(
    folder: Callable[[Path], str], program: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A writer of the folder (or of one above it) can rename an older record over the NV file:
    refused before the bus is opened, in Python's words (``check_private_dir``)."""
    binary = built(f"build/{program}")
    nv = folder(tmp_path)
    before = sorted(p.name for p in tmp_path.rglob("*"))
    run = run_without_bus(binary, tmp_path, "--nv", nv)
    refused(run, "is writable by others, who can replace or roll back the file; chmod go-w")
    assert run.stderr == f"{program}: error: {_python_refusal(nv, tmp_path, monkeypatch)}\n"
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing created


@pytest.mark.parametrize("program", ["canergy-node", "canergy-gateway"])
def test_the_c_programs_take_a_sticky_or_private_nv_folder(program: str, tmp_path: Path) -> None:
    """A sticky folder (as /tmp) lets no one else rename over the file; a private one neither."""
    binary = built(f"build/{program}")
    for name, mode in (("sticky", 0o1777), ("private", 0o700), ("readable", 0o755)):
        (tmp_path / name).mkdir(mode=0o700)
        (tmp_path / name).chmod(mode)
        run = run_without_bus(binary, tmp_path, "--nv", f"{name}/n.nv")
        assert run.returncode == 2 and "CAN socket" in run.stderr, run.stderr  # the bus


@pytest.mark.skipif(os.geteuid() != 0, reason="giving a folder away needs root")
@pytest.mark.parametrize("program", ["canergy-node", "canergy-gateway"])
def test_the_c_programs_refuse_an_nv_folder_of_another_user(
    program: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    binary = built(f"build/{program}")
    (tmp_path / "theirs").mkdir(mode=0o755)
    os.chown(tmp_path / "theirs", 54321, -1)
    run = run_without_bus(binary, tmp_path, "--nv", "theirs/n.nv")
    refused(run, f"directory {tmp_path / 'theirs'} belongs to user 54321")
    expected = _python_refusal("theirs/n.nv", tmp_path, monkeypatch)
    assert run.stderr == f"{program}: error: {expected}\n"


# --- the key files' folders and modes: refused where Python refuses them, in its words --------

KEY_FLAGS = [("canergy-node", "--auth"), ("canergy-gateway", "--upstream-auth")]
KEY_FLAGS += [("canergy-gateway", "--auth")]
"""Each C program and flag that reads a key file: node 1's key, the gateway's own master key
below (``--auth``)."""
KEY_IDS = [f"{program}{flag}" for program, flag in KEY_FLAGS]


def _key_for(flag: str, program: str, tmp: Path, key: str) -> None:
    """A key ``flag`` of ``program`` takes, written at ``key`` (relative to ``tmp``, mode 0600)."""
    path = tmp / os.path.normpath(key)  # lexically, as written: nosuchdir/.. is no folder
    master = new_master(1)
    write_key(
        path, master if (program, flag) == ("canergy-gateway", "--auth") else node_key_of(master, 1)
    )


def _python_key_verdict(flag: str, key: str, tmp: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    """What Python says of the key file ``key`` (relative to ``tmp``) given for ``flag``: its
    folders (``check_private_dir``, as ``canergy gateway``, ``supervisor`` and ``python -m
    firmware_model`` check them), then the file (``load_key``, its refusal after the flag as
    ``canergy gateway`` words it); "" when it takes it."""
    monkeypatch.chdir(tmp)
    try:
        check_private_dir(Path(key), flag)
        load_key(Path(key))
    except PermissionError as exc:
        return str(exc)
    except KeyFileError as exc:
        return f"{flag} {exc}"
    return ""


def _run_with_key(program: str, flag: str, tmp: Path, key: str) -> subprocess.CompletedProcess[str]:
    return run_without_bus(built(f"build/{program}"), tmp, "--nv", "rec.nv", flag, key)


def _refused_as_python(
    program: str, flag: str, tmp: Path, key: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Python refuses ``key``, and the C program refuses it in the same words, byte for byte,
    exit 2, before anything is created or the bus opened."""
    words = _python_key_verdict(flag, key, tmp, monkeypatch)
    assert words, f"Python takes {flag} {key}"
    before = sorted(p.name for p in tmp.rglob("*"))
    run = _run_with_key(program, flag, tmp, key)
    assert run.returncode == 2, run.stderr
    assert run.stderr == f"{program}: error: {words}\n"
    assert sorted(p.name for p in tmp.rglob("*")) == before  # no NV record


@pytest.mark.parametrize(("program", "flag"), KEY_FLAGS, ids=KEY_IDS)
@pytest.mark.parametrize("folder", OPEN_FOLDERS, ids=lambda f: f.__name__[1:])
def test_the_c_programs_refuse_a_key_folder_others_may_write_as_python_does(
    folder: Callable[[Path], str],
    program: str,
    flag: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A writer of the key's folder (or of one above it, as written or once symlinks are
    resolved) can put another key there: refused as ``check_private_dir`` refuses it."""
    key = folder(tmp_path)
    _key_for(flag, program, tmp_path, key)
    _refused_as_python(program, flag, tmp_path, key, monkeypatch)
    assert "is writable by others" in _python_key_verdict(flag, key, tmp_path, monkeypatch)


@pytest.mark.skipif(os.geteuid() != 0, reason="giving a folder away needs root")
@pytest.mark.parametrize(("program", "flag"), KEY_FLAGS, ids=KEY_IDS)
def test_the_c_programs_refuse_a_key_folder_of_another_user(
    program: str, flag: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "theirs").mkdir(mode=0o755)
    _key_for(flag, program, tmp_path, "theirs/k.key")
    os.chown(tmp_path / "theirs", 54321, -1)
    _refused_as_python(program, flag, tmp_path, "theirs/k.key", monkeypatch)
    assert "belongs to user 54321" in _python_key_verdict(
        flag, "theirs/k.key", tmp_path, monkeypatch
    )


@pytest.mark.parametrize(("program", "flag"), KEY_FLAGS, ids=KEY_IDS)
@pytest.mark.parametrize("mode", [0o640, 0o604, 0o620, 0o602, 0o610, 0o601], ids=oct)
def test_the_c_programs_refuse_a_key_file_others_may_read_or_write_as_python_does(
    mode: int, program: str, flag: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _key_for(flag, program, tmp_path, "k.key")
    (tmp_path / "k.key").chmod(mode)
    _refused_as_python(program, flag, tmp_path, "k.key", monkeypatch)
    assert f"mode {mode:04o} lets others read it" in _python_key_verdict(
        flag, "k.key", tmp_path, monkeypatch
    )


@pytest.mark.parametrize(("program", "flag"), KEY_FLAGS, ids=KEY_IDS)
def test_the_c_programs_take_a_key_where_python_does(
    program: str, flag: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A sticky folder (as /tmp), a private or a readable one, a key file of mode 0600, 0400 or
    0700, and (as root) one another user owns, 0600: Python takes each, and so does the C
    program (the bus, which does not exist here, is what stops it)."""
    keys = []
    for name, mode in (("sticky", 0o1777), ("private", 0o700), ("readable", 0o755)):
        (tmp_path / name).mkdir(mode=0o700)
        (tmp_path / name).chmod(mode)
        keys.append(f"{name}/k.key")
        _key_for(flag, program, tmp_path, keys[-1])
    for mode in (0o400, 0o700):
        keys.append(f"private/{mode:o}.key")
        _key_for(flag, program, tmp_path, keys[-1])
        (tmp_path / keys[-1]).chmod(mode)
    if os.geteuid() == 0:
        keys.append("private/theirs.key")
        _key_for(flag, program, tmp_path, keys[-1])
        os.chown(tmp_path / keys[-1], 54321, -1)
    for key in keys:
        assert _python_key_verdict(flag, key, tmp_path, monkeypatch) == "", key
        run = _run_with_key(program, flag, tmp_path, key)
        assert run.returncode == 2 and "CAN socket" in run.stderr, (key, run.stderr)


def test_the_c_gateway_checks_its_key_folders_in_pythons_order(
    c_gateway: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Both keys in a folder others may write: ``--auth``'s is named first, as ``canergy
    gateway``'s ``check_state`` names it (the books' key before the key above)."""
    key = _world_writable(tmp_path)
    _key_for("--upstream-auth", "canergy-gateway", tmp_path, key)
    _key_for("--auth", "canergy-gateway", tmp_path, "d/own.key")
    run = run_without_bus(
        c_gateway, tmp_path, "--nv", "g.nv", "--upstream-auth", key, "--auth", "d/own.key"
    )
    words = _python_key_verdict("--auth", "d/own.key", tmp_path, monkeypatch)
    assert words.startswith(f"--auth d/own.key: directory {tmp_path / 'd'} (mode 0777)"), words
    assert run.returncode == 2 and run.stderr == f"canergy-gateway: error: {words}\n"


def _linked_into_an_open_folder(tmp: Path, target: str) -> str:
    """A private folder ``p`` holding a symlink ``p/file`` to ``open/<target>``, ``open`` a
    folder anyone may write: the file's folder as written and resolved is private, its
    target's is not. Returns the link, relative to ``tmp``."""
    (tmp / "open").mkdir(mode=0o700)
    (tmp / "open").chmod(0o777)
    (tmp / "p").mkdir(mode=0o700)
    (tmp / "p" / "file").symlink_to(Path("..") / "open" / target)
    return "p/file"


@pytest.mark.parametrize(("program", "flag"), KEY_FLAGS, ids=KEY_IDS)
def test_the_c_programs_refuse_a_key_linked_into_a_folder_others_may_write_as_python_does(
    program: str, flag: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Anyone who may write the target's folder can swap the key the link points at: the
    link's own folder being private does not make the key private."""
    key = _linked_into_an_open_folder(tmp_path, "real.key")
    _key_for(flag, program, tmp_path, "open/real.key")
    words = _python_key_verdict(flag, key, tmp_path, monkeypatch)
    assert f"directory {tmp_path / 'open'} (mode 0777) is writable by others" in words, words
    _refused_as_python(program, flag, tmp_path, key, monkeypatch)


@pytest.mark.parametrize("program", ["canergy-node", "canergy-gateway"])
@pytest.mark.parametrize("dangling", [False, True], ids=["existing", "dangling"])
def test_the_c_programs_refuse_an_nv_record_linked_into_a_folder_others_may_write(
    program: str, dangling: bool, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The NV record a symlink to a file (or to no file yet) in a folder anyone may write:
    refused in Python's words, before anything is created."""
    nv = _linked_into_an_open_folder(tmp_path, "n.nv")
    if not dangling:
        (tmp_path / "open" / "n.nv").write_bytes(b"")
    before = sorted(p.name for p in tmp_path.rglob("*"))
    run = run_without_bus(built(f"build/{program}"), tmp_path, "--nv", nv)
    words = _python_refusal(nv, tmp_path, monkeypatch)
    assert f"directory {tmp_path / 'open'} (mode 0777)" in words, words
    assert run.returncode == 2 and run.stderr == f"{program}: error: {words}\n"
    assert sorted(p.name for p in tmp_path.rglob("*")) == before
