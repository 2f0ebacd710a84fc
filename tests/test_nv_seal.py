"""The NV seal (firmware/include/canergy/nv.h, "Sealed image"; firmware_model/nvstore.py): a node
or gateway run with a key seals each NV record slot with 8 bytes of AES-CMAC under a key derived
from its own, so a local user who can write the NV file but holds no key cannot raise a node's
usable energy or lower its last_tx: the slot is set aside as a damaged one (the other taken),
and with none left the node refuses to start, naming the file. A record never sealed is refused
by a keyed node; a sealed file is refused without the key; without a key nothing changes.

Checked in the library (cffi), in firmware_model's store, and in the C node's and gateway's
processes (refused before the bus is opened: no vcan0).
"""

from __future__ import annotations

import signal
import struct
import subprocess
import zlib
from pathlib import Path

import pytest
from cryptography.hazmat.primitives.ciphers import algorithms
from cryptography.hazmat.primitives.cmac import CMAC
from support.c_binding import NvState, Struct, cbuf, library, ref, struct_bytes
from support.firmware_build import c_gateway as c_gateway  # the fixtures
from support.firmware_build import c_node as c_node
from support.firmware_build import refused, run_without_bus

import firmware_model.__main__ as firmware
from canergy.auth.keys import Key, new_master, node_key_of, write_key
from canergy.auth.state_key import derive
from canergy.core.state import ClientState, Outcome
from firmware_model.node import FirmwareNode, NodeHost
from firmware_model.nvstore import (
    SEAL_SIZE,
    SEALED_SIZE,
    SEALS_AT,
    SLOT_SIZE,
    NvError,
    NvSeal,
    NvStore,
    pack_record,
)

Cmac = Struct("cmac")
MASTER = new_master(1)
KEY1, KEY2 = node_key_of(MASTER, 1), node_key_of(MASTER, 2)


def _record(usable: int, last_tx: int) -> ClientState:
    return ClientState(
        1,
        usable=usable,
        credited=50_000_000,
        spent=50_000_000 - usable,
        last_tx=last_tx,
        outcome=Outcome.COMMITTED,
    )


def _sealed_file(path: Path, key: bytes = KEY1.secret, node: int = 1) -> Path:
    """Two genuine records, sealed: slot 0 (counter 1) 3 J at tx 4, slot 1 (counter 2) 2 J at
    tx 7, the newest."""
    store = NvStore(path, node, fsync=False, seal=NvSeal(key, node))
    store.save(_record(3_000_000, 4))
    store.save(_record(2_000_000, 7))
    store.close()
    return path


def _edit(path: Path, slot: int, usable: int | None = None, last_tx: int | None = None) -> None:
    """What a local user without the key can do: change a field, recompute the CRC; the seal
    stays as it was."""
    raw = bytearray(path.read_bytes())
    at = slot * SLOT_SIZE + 6  # the record after magic and counter
    if usable is not None:
        raw[at : at + 4] = struct.pack("<I", usable)
    if last_tx is not None:
        raw[at + 16 : at + 20] = struct.pack("<I", last_tx)
    end = (slot + 1) * SLOT_SIZE - 4
    raw[end : end + 4] = struct.pack("<I", zlib.crc32(bytes(raw[slot * SLOT_SIZE : end])))
    path.write_bytes(bytes(raw))


# --- the library ------------------------------------------------------------------------------


def _c_seal_key(key: bytes, node: int, gateway: bool = False) -> object:
    seal = Cmac()
    library().canergy_nv_seal_key(ref(seal), key, node, gateway)
    return seal


def _c_unseal(image: bytes, key: bytes, node: int = 1) -> tuple[int, bytes]:
    buf = cbuf(image)
    spoilt = library().canergy_nv_unseal(
        ref(_c_seal_key(key, node)), buf, len(image), SLOT_SIZE, 2, buf + SEALS_AT
    )
    return spoilt, struct_bytes(buf)[: len(image)]


def _c_load(image: bytes) -> NvState:
    state = NvState()
    library().canergy_nv_load(cbuf(image), len(image), ref(state))
    return state


def test_c_and_python_make_the_same_seal_under_a_key_of_its_own(tmp_path: Path) -> None:
    raw = _sealed_file(tmp_path / "n.nv").read_bytes()
    assert len(raw) == SEALED_SIZE
    for slot in (0, 1):
        image = raw[slot * SLOT_SIZE : (slot + 1) * SLOT_SIZE]
        seal = cbuf(SEAL_SIZE)
        library().canergy_nv_seal(ref(_c_seal_key(KEY1.secret, 1)), image, SLOT_SIZE, seal)
        found = raw[SEALS_AT + slot * SEAL_SIZE : SEALS_AT + (slot + 1) * SEAL_SIZE]
        assert struct_bytes(seal) == found
        # the key of no frame MAC (the node key itself) nor of the gateway's seal
        for other in (KEY1.secret, derive(KEY1.secret, b"canergy gateway nv seal", b"\x01")):
            c = CMAC(algorithms.AES(other))
            c.update(image)
            assert c.finalize()[:SEAL_SIZE] != found
    assert _c_unseal(raw, KEY1.secret) == (0, raw)


def test_an_edited_slot_is_spoilt_in_c_and_the_older_genuine_one_taken(tmp_path: Path) -> None:
    path = _sealed_file(tmp_path / "n.nv")
    _edit(path, 1, usable=900_000_000)
    raw = path.read_bytes()
    assert _c_load(raw).record.usable_uj == 900_000_000  # the CRC holds: without the seal, taken
    spoilt, image = _c_unseal(raw, KEY1.secret)
    state = _c_load(image)
    assert spoilt == 0b10 and state.books and state.newest_slot == 0 and state.fallbacks == 1
    assert (state.record.usable_uj, state.record.last_tx) == (3_000_000, 4)


def test_a_seal_does_not_hold_under_another_nodes_key(tmp_path: Path) -> None:
    raw = _sealed_file(tmp_path / "n.nv").read_bytes()
    spoilt, image = _c_unseal(raw, KEY2.secret, 1)
    assert spoilt == 0b11 and not _c_load(image).books
    assert _c_unseal(raw, KEY1.secret, 2)[0] == 0b11  # the node id is in the key's context
    with pytest.raises(NvError, match="the seal does not hold"):
        NvStore(tmp_path / "n.nv", 1, seal=NvSeal(KEY2.secret, 1)).load()


# --- firmware_model's store -------------------------------------------------------------------


@pytest.mark.parametrize(
    ("field", "edit"), [("usable raised", {"usable": 900_000_000}), ("ltx lowered", {"last_tx": 1})]
)
def test_an_edited_newest_record_is_set_aside(
    field: str, edit: dict[str, int], tmp_path: Path
) -> None:
    path = _sealed_file(tmp_path / "n.nv")
    _edit(path, 1, **edit)
    store = NvStore(path, 1, seal=NvSeal(KEY1.secret, 1))
    record = store.load()
    assert record is not None and (record.usable, record.last_tx) == (3_000_000, 4), field
    assert store.set_aside == [1] and store.stats.fallbacks == 1


def test_both_records_edited_refuse_the_start(tmp_path: Path) -> None:
    path = _sealed_file(tmp_path / "n.nv")
    _edit(path, 0, usable=900_000_000)
    _edit(path, 1, last_tx=1)
    with pytest.raises(NvError) as refused:
        NvStore(path, 1, seal=NvSeal(KEY1.secret, 1)).load()
    assert str(refused.value).startswith(f"--nv {path}: node 1: slot 0 and 1: the seal does not")


def test_a_keyed_store_refuses_a_record_never_sealed(tmp_path: Path) -> None:
    path = tmp_path / "n.nv"
    NvStore(path, 1, fsync=False).save(_record(2_000_000, 7))
    with pytest.raises(NvError, match="slot 0 holds a record that is not sealed"):
        NvStore(path, 1, seal=NvSeal(KEY1.secret, 1)).load()
    new = NvStore(tmp_path / "new.nv", 1, fsync=False, seal=NvSeal(KEY1.secret, 1))
    assert new.load() is None  # a new file: JOIN, then sealed from the first write
    new.save(_record(0, 0))
    assert (tmp_path / "new.nv").stat().st_size == SEALED_SIZE


def test_without_a_key_nothing_changes_and_a_sealed_file_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "n.nv"
    store = NvStore(path, 1, fsync=False)
    store.save(_record(3_000_000, 4))
    store.save(_record(2_000_000, 7))
    assert path.stat().st_size == 2 * SLOT_SIZE
    _edit(path, 1, usable=900_000_000)  # no key, no seal: the edit is taken, as before
    record = NvStore(path, 1).load()
    assert record is not None and record.usable == 900_000_000
    with pytest.raises(NvError, match="sealed by a node with a key"):
        NvStore(_sealed_file(tmp_path / "s.nv"), 1).load()


# --- the C node's and gateway's processes -----------------------------------------------------


def _key_file(tmp: Path, key: Key, name: str = "n1.key") -> str:
    write_key(tmp / name, key)
    return str(tmp / name)


def _past_the_nv_checks(run: subprocess.CompletedProcess[str]) -> None:
    """Stopped by the bus that does not exist, after every NV check."""
    bus = "nosuchcan" in run.stderr or "CAN socket" in run.stderr
    assert run.returncode == 2 and bus and "--nv" not in run.stderr, run.stderr


@pytest.mark.parametrize("edit", [{"usable": 900_000_000}, {"last_tx": 1}])
def test_the_c_node_refuses_a_record_edited_without_the_key(
    edit: dict[str, int], c_node: Path, tmp_path: Path
) -> None:
    key = _key_file(tmp_path, KEY1)
    path = _sealed_file(tmp_path / "n.nv")
    _past_the_nv_checks(run_without_bus(c_node, tmp_path, "--nv", "n.nv", "--auth", key))
    _edit(path, 1, **edit)  # the other genuine: taken (past the checks, to the bus)
    _past_the_nv_checks(run_without_bus(c_node, tmp_path, "--nv", "n.nv", "--auth", key))
    _edit(path, 0, **edit)
    before = path.read_bytes()
    run = run_without_bus(c_node, tmp_path, "--nv", "n.nv", "--auth", key)
    refused(run, "canergy-node: error: --nv n.nv: node 1: slot 0 and 1: the seal does not hold")
    assert "nothing taken" in run.stderr and path.read_bytes() == before


def test_the_c_node_takes_no_record_sealed_under_another_nodes_key(
    c_node: Path, tmp_path: Path
) -> None:
    _sealed_file(tmp_path / "n.nv", KEY2.secret, 1)
    run = run_without_bus(c_node, tmp_path, "--nv", "n.nv", "--auth", _key_file(tmp_path, KEY1))
    refused(run, "slot 0 and 1: the seal does not hold (the record edited, or sealed under")


def test_the_c_node_with_a_key_refuses_an_unsealed_record_and_without_one_a_sealed(
    c_node: Path, tmp_path: Path
) -> None:
    NvStore(tmp_path / "plain.nv", 1, fsync=False).save(_record(2_000_000, 7))
    key = _key_file(tmp_path, KEY1)
    run = run_without_bus(c_node, tmp_path, "--nv", "plain.nv", "--auth", key)
    refused(run, "--nv plain.nv: node 1: slot 0 holds a record that is not sealed")
    _past_the_nv_checks(run_without_bus(c_node, tmp_path, "--nv", "plain.nv"))  # no key: as before
    _sealed_file(tmp_path / "sealed.nv")
    refused(
        run_without_bus(c_node, tmp_path, "--nv", "sealed.nv"),
        "sealed by a node with a key (--auth)",
    )


GW_NODES = 127  # CANERGY_SUPERVISOR_NODES of canergy-gateway's build
GW_SLOT = 8 + 30 + 40 + 56 * GW_NODES + 4


def _gateway_slot(counter: int, usable: int) -> bytes:
    """A canergy-gateway slot: its record above, the supervisor's image below with node 2 idle
    (firmware/src/supervisor.c's layout, version 5), each with its CRC."""
    head = struct.pack("<IBBBBIQQQ", 0x534E5243, 5, 1, 0, 0, 1, 0, 0, 0)
    body = head + struct.pack("<BBBBIIIQQ6I", 2, 0, 0, 0, 0, 0, 0, 0, 0, *[0] * 6)
    below = (body + struct.pack("<I", zlib.crc32(body))).ljust(40 + 56 * GW_NODES, b"\0")
    slot = struct.pack("<II", 0x47524E43, counter) + pack_record(_record(usable, 4)) + below
    return slot + struct.pack("<I", zlib.crc32(slot))


def _gateway_file(path: Path, key: bytes | None) -> Path:
    """Two gateway slots (counters 1, 2), sealed under ``key``'s gateway seal key when given."""
    slots = _gateway_slot(1, 1_000_000) + _gateway_slot(2, 2_000_000)
    assert len(slots) == 2 * GW_SLOT
    seals = b""
    if key is not None:
        seal_key = derive(key, b"canergy gateway nv seal", b"\x01")
        for i in (0, 1):
            c = CMAC(algorithms.AES(seal_key))
            c.update(slots[i * GW_SLOT : (i + 1) * GW_SLOT])
            seals += c.finalize()[:SEAL_SIZE]
    path.write_bytes(slots + seals)
    return path


def _gw_edit(path: Path, slot: int) -> None:
    raw = bytearray(path.read_bytes())
    at = slot * GW_SLOT
    raw[at + 8 : at + 12] = struct.pack("<I", 900_000_000)  # the upstream record's usable
    end = at + GW_SLOT - 4
    raw[end : end + 4] = struct.pack("<I", zlib.crc32(bytes(raw[at:end])))
    path.write_bytes(bytes(raw))


def test_the_c_gateway_seals_under_its_key_and_refuses_edits(
    c_gateway: Path, tmp_path: Path
) -> None:
    key = _key_file(tmp_path, KEY1)
    up = ("--upstream-auth", key)
    path = _gateway_file(tmp_path / "g.nv", KEY1.secret)
    _past_the_nv_checks(run_without_bus(c_gateway, tmp_path, "--nv", "g.nv", *up))
    _gw_edit(path, 1)
    _past_the_nv_checks(run_without_bus(c_gateway, tmp_path, "--nv", "g.nv", *up))  # slot 0 genuine
    _gw_edit(path, 0)
    run = run_without_bus(c_gateway, tmp_path, "--nv", "g.nv", *up)
    refused(run, "canergy-gateway: error: --nv g.nv: slot 0 and 1: the seal does not hold")
    _gateway_file(path, KEY2.secret)  # another key's seal
    refused(run_without_bus(c_gateway, tmp_path, "--nv", "g.nv", *up), "the seal does not hold")


def test_the_c_gateway_with_a_key_refuses_an_unsealed_record_and_without_one_a_sealed(
    c_gateway: Path, tmp_path: Path
) -> None:
    key = _key_file(tmp_path, KEY1)
    _gateway_file(tmp_path / "plain.nv", None)
    run = run_without_bus(c_gateway, tmp_path, "--nv", "plain.nv", "--upstream-auth", key)
    refused(run, "--nv plain.nv: a record that is not sealed")
    _past_the_nv_checks(
        run_without_bus(c_gateway, tmp_path, "--nv", "plain.nv")
    )  # no key: as before
    _gateway_file(tmp_path / "sealed.nv", KEY1.secret)
    refused(
        run_without_bus(c_gateway, tmp_path, "--nv", "sealed.nv"), "sealed by a gateway with a key"
    )


def test_the_c_gateway_seals_with_its_master_key_below_when_no_key_above(
    c_gateway: Path, tmp_path: Path
) -> None:
    master, own = tmp_path / "gw.key", new_master(1)
    write_key(master, own)
    _gateway_file(tmp_path / "g.nv", own.secret)
    _past_the_nv_checks(run_without_bus(c_gateway, tmp_path, "--nv", "g.nv", "--auth", str(master)))
    _gateway_file(tmp_path / "g.nv", KEY1.secret)
    refused(
        run_without_bus(c_gateway, tmp_path, "--nv", "g.nv", "--auth", str(master)),
        "seal does not hold",
    )


# --- python -m firmware_model --auth ----------------------------------------------------------


class _Served(Exception):
    """The emulator got past its start-up (its node and NV record built) and would now run."""


def _emulate(
    monkeypatch: pytest.MonkeyPatch, tmp: Path, *args: str
) -> tuple[int | str | None, list[FirmwareNode]]:
    """``firmware_model.main`` in ``tmp`` up to where it would serve: its exit status (None:
    served) and the nodes it built."""
    built: list[FirmwareNode] = []

    def serve(args: object, host: NodeHost, *rest: object) -> None:
        built.extend(host.nodes.values())
        raise _Served

    monkeypatch.setattr(firmware, "_serve", serve)
    monkeypatch.chdir(tmp)
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1)}
    nodes: list[FirmwareNode] = []  # the caller's alone (monkeypatch keeps ``serve``)
    try:
        firmware.main(["--node", "1", *args, "-i", "virtual", "--no-fsync"])
    except SystemExit as exc:
        return exc.code, nodes
    except _Served:
        return None, nodes
    finally:
        for number, handler in handlers.items():
            signal.signal(number, handler)
        nodes += built
        built.clear()
    raise AssertionError("neither served nor exited")


def test_the_emulator_with_its_key_takes_the_genuine_record_and_refuses_edits(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    key = _key_file(tmp_path, KEY1)
    path = _sealed_file(tmp_path / "n.nv")
    _edit(path, 1, usable=900_000_000)
    code, nodes = _emulate(monkeypatch, tmp_path, "--nv", "n.nv", "--auth", key)
    assert code is None and nodes[0].client.state.usable == 3_000_000  # the older, genuine
    del nodes  # the node that keeps the record (its NV file locked) is gone
    _edit(path, 0, last_tx=1)
    code, nodes = _emulate(monkeypatch, tmp_path, "--nv", "n.nv", "--auth", key)
    err = capsys.readouterr().err
    assert code == 2 and not nodes and "n.nv: node 1: slot 0 and 1: the seal does not hold" in err
