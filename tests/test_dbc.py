"""The published DBC agrees with the codec, checked through cantools in both directions."""

from pathlib import Path

import cantools
import pytest
from hypothesis import given
from support.strategies import messages

from canergy.codec import XOR_OUT, Codec, _prefix_register
from canergy.crc import crc8_update
from canergy.dbc import dbc_text
from canergy.messages import Message, Telemetry

DBC_PATH = Path(__file__).parent.parent / "dbc" / "canergy.dbc"
CODEC = Codec()


_db_cache: list[cantools.database.can.Database] = []


def _db() -> cantools.database.can.Database:
    if not _db_cache:
        _db_cache.append(cantools.database.load_file(str(DBC_PATH)))
    return _db_cache[0]


def _raw_signals(msg: Message) -> dict[str, int]:
    names = {
        "tx": "TX",
        "seq": "SEQ",
        "amount_mj": "AMOUNT",
        "delivered_mj": "DELIVERED",
        "level_mj": "LEVEL",
        "flags": "FLAGS",
        "return_seq": "RETURN_SEQ",
        "witness": "WITNESS",
    }
    return {sig: getattr(msg, field) for field, sig in names.items() if hasattr(msg, field)}


def test_committed_dbc_is_what_the_codec_generates() -> None:
    expected = dbc_text(CODEC.id_base).encode()
    assert DBC_PATH.read_bytes() == expected, "regenerate: canergy dbc -o dbc/canergy.dbc"


@given(messages)
def test_cantools_decodes_our_frames(msg: Message) -> None:
    arbitration_id, data = CODEC.encode(msg)
    decoded = _db().decode_message(arbitration_id, data, scaling=False)
    assert decoded == {"CRC": data[0], **_raw_signals(msg)}


@given(messages)
def test_we_decode_frames_cantools_encodes(msg: Message) -> None:
    arbitration_id = CODEC.arbitration_id(msg.TYPE, msg.node)
    frame = _db().get_message_by_frame_id(arbitration_id)
    assert frame.is_extended_frame
    unsigned = frame.encode({"CRC": 0, **_raw_signals(msg)}, scaling=False)
    crc = crc8_update(_prefix_register(msg.TYPE, msg.node), unsigned[1:]) ^ XOR_OUT
    signed = frame.encode({"CRC": crc, **_raw_signals(msg)}, scaling=False)
    assert CODEC.decode(arbitration_id, signed) == msg


def test_amounts_decode_in_joules() -> None:
    from canergy.messages import Intention

    db = _db()
    arbitration_id, data = CODEC.encode(Intention(7, 3, 2500, 1234))
    decoded = db.decode_message(arbitration_id, data)
    assert decoded["AMOUNT"] == pytest.approx(2.5)
    assert decoded["DELIVERED"] == pytest.approx(1.234)
    assert db.get_message_by_frame_id(arbitration_id).name == "INTENTION_N7"


def test_cantools_cli_decodes_candump_output() -> None:
    """`candump vcan0 | cantools decode dbc/canergy.dbc`, with candump's default line format."""
    import subprocess
    import sys

    from canergy.messages import Ack, Intention

    lines = []
    for msg in (Intention(5, 1, 500, 0), Ack(5, 1)):
        arbitration_id, data = CODEC.encode(msg)
        hex_bytes = " ".join(f"{b:02X}" for b in data)
        lines.append(f"  vcan0  {arbitration_id:08X}   [{len(data)}]  {hex_bytes}")
    out = subprocess.run(
        [sys.executable, "-m", "cantools", "decode", "--single-line", str(DBC_PATH)],
        input="\n".join(lines) + "\n",
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert "INTENTION_N5(CRC: 41, TX: 1, AMOUNT: 0.5 J, DELIVERED: 0.0 J)" in out
    assert "ACK_N5(CRC: 69, TX: 1)" in out


AUTH_KEY = bytes(range(16))


@pytest.mark.parametrize("layout", ["fd", "classic"])
def test_committed_authenticated_dbcs_are_what_the_codec_generates(layout: str) -> None:
    path = DBC_PATH.with_name(f"canergy-auth-{layout}.dbc")
    expected = dbc_text(CODEC.id_base, layout).encode()
    assert path.read_bytes() == expected, f"regenerate: canergy dbc --auth {layout} -o {path}"


@pytest.mark.parametrize("layout", ["fd", "classic"])
@given(messages)
def test_cantools_decodes_authenticated_frames(layout: str, msg: Message) -> None:
    from canergy.auth.frames import FrameAuth, Layout, freshness
    from canergy.messages import Direction

    db = _auth_db(layout)
    auth = FrameAuth(
        CODEC,
        Layout(layout),
        lambda n: AUTH_KEY,
        Direction.TO_CLIENT,
        lambda m: freshness(m, 70_000, 3),
    )
    frames = auth.frames(msg)
    fv = freshness(msg, 70_000, 3)
    first = db.decode_message(frames[0].arbitration_id, bytes(frames[0].data), scaling=False)
    assert {k: v for k, v in first.items() if k in _raw_signals(msg)} == _raw_signals(msg)
    if layout == "fd":
        assert first["FV"] == fv and first["MAC"] == int.from_bytes(frames[0].data[-8:], "big")
    else:
        trailer = db.decode_message(frames[1].arbitration_id, bytes(frames[1].data), scaling=False)
        half = fv & 0xFFFF if isinstance(msg, Telemetry) else fv >> 16
        assert trailer["MSG_TYPE"] == msg.TYPE and trailer["FV_HALF"] == half
        assert trailer["MAC"] == int.from_bytes(frames[1].data[3:], "big")


_auth_dbs: dict[str, cantools.database.can.Database] = {}


def _auth_db(layout: str) -> cantools.database.can.Database:
    if layout not in _auth_dbs:
        path = DBC_PATH.with_name(f"canergy-auth-{layout}.dbc")
        _auth_dbs[layout] = cantools.database.load_file(str(path))
    return _auth_dbs[layout]


def test_cantools_reads_the_rules_flag_of_a_witnessed_nodes_telemetry(tmp_path: Path) -> None:
    """FLAGS bit 3 (``Telemetry.WITNESSED``): set by a node under the witnessed rules, named in
    the signal's comment (review rv3, F3)."""
    from firmware_model.node import FirmwareNode, NodeConfig
    from firmware_model.nvstore import NvStore

    db = _db()
    for variant, flag in (("witnessed", Telemetry.WITNESSED), ("hardened", 0)):
        nv = NvStore(tmp_path / f"{variant}.nv", 3, fsync=False)
        node = FirmwareNode(3, nv, NodeConfig(variant=variant), 0)
        arbitration_id, data = CODEC.encode(node.telemetry(0))
        assert db.decode_message(arbitration_id, data)["FLAGS"] & 0x08 == flag
    comment = db.get_message_by_frame_id(arbitration_id).get_signal_by_name("FLAGS").comment
    assert "bit 3: the witnessed client rules" in comment
