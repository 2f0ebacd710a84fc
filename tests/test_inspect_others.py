"""``canergy decode``/``dump`` name other protocols' frames beside canergy's: a user's DBC (the
ODrive DBC odrive-can installs), ODrive CAN Simple by node id, CANopen's predefined set."""

from __future__ import annotations

import json
from pathlib import Path

import odrive_can
import pytest

from canergy.cli import main
from canergy.inspect.others import Dbc, Namer, canopen

ODRIVE_DBC = Path(odrive_can.__file__).parent / "dbc" / "odrive-cansimple-0.6.10.dbc"
LOG = """\
(1700000000.000000) vcan0 705#05
(1700000000.001000) vcan0 605#2B726000E8030000
(1700000000.002000) vcan0 585#8072600000000906
(1700000000.003000) vcan0 000#8105
(1700000000.004000) vcan0 069#0000803F00000040
(1700000000.005000) vcan0 085#1032040000000000
(1700000000.006000) vcan0 7FF#00
(1700000000.007000) vcan0 069#00
"""


def _decode(tmp_path: Path, capsys: pytest.CaptureFixture[str], *flags: str) -> list[str]:
    log = tmp_path / "bench.log"
    log.write_text(LOG)
    assert main(["decode", "--json", *flags, str(log)]) == 0
    return capsys.readouterr().out.splitlines()


def _others(lines: list[str]) -> list[dict[str, object] | None]:
    return [json.loads(line)["other"] for line in lines]


def test_canopen_frames_are_named_by_default(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    got = _others(_decode(tmp_path, capsys))
    assert [(o["name"], o["node"]) if o else None for o in got] == [
        ("heartbeat", 5),
        ("SDO request", 5),
        ("SDO answer", 5),
        ("NMT", None),
        None,  # 0x069 is no CANopen function code
        ("EMCY", 5),
        None,  # 0x7FF: in 0x780-0x7FF (LSS and others), not named
        None,
    ]
    assert got[1]["fields"] == {"command": "download", "object": "0x6072:00", "value": "0x03E8"}
    assert got[2]["fields"]["code"] == "0x06090000"  # abort: sub-index does not exist
    assert got[3]["fields"] == {"command": "reset", "to": 5}
    assert got[5]["fields"] == {"code": "0x3210", "register": "0x04"}
    assert _others(_decode(tmp_path, capsys, "--no-canopen")) == [None] * len(got)


def test_a_dbc_names_and_decodes_its_frames_first(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    got = _others(_decode(tmp_path, capsys, "--dbc", str(ODRIVE_DBC)))
    estimates = got[4]
    assert estimates is not None and estimates["protocol"] == "dbc:odrive-cansimple-0.6.10.dbc"
    assert estimates["name"] == "Axis3_Get_Encoder_Estimates"
    assert estimates["fields"] == {"Pos_Estimate": 1.0, "Vel_Estimate": 2.0}
    short = got[7]  # one byte where the DBC says eight: named, not decoded, no error
    assert short is not None and short["name"] == "Axis3_Get_Encoder_Estimates"
    assert short["problem"] and short["problem"].startswith("not decoded")


def test_odrive_node_ids_name_can_simple(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    got = _others(_decode(tmp_path, capsys, "--odrive-names", "3"))
    assert got[4] == {
        "protocol": "odrive",
        "name": "encoder_estimates",
        "node": 3,
        "fields": {"pos_rev": 1.0, "vel_rev_s": 2.0},
        "problem": None,
    }
    text = Namer(odrive_nodes=[3]).name(0x069, False, False, b"\x00" * 8)
    assert text is not None and text.text().startswith("odrive: encoder_estimates 3")


def test_the_text_view_shows_the_names(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "bench.log"
    log.write_text(LOG)
    assert main(["decode", str(log)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].endswith("canopen: heartbeat 5  state OPERATIONAL")
    assert "SDO request 5  command download  object 0x6072:00  value 0x03E8" in lines[1]


@pytest.mark.parametrize(
    "data", [b"", b"\x2b", b"\x2b\x72\x60", bytes(9), b"\xff" * 8, b"\x00" * 7]
)
@pytest.mark.parametrize("ident", [0x000, 0x080, 0x085, 0x185, 0x585, 0x605, 0x705])
def test_malformed_canopen_frames_are_named_never_raised(ident: int, data: bytes) -> None:
    named = canopen(ident, data)
    assert named is not None and named.text()


def test_a_file_that_is_no_dbc_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.dbc"
    bad.write_text("BO_ this is not a DBC\n")
    with pytest.raises(SystemExit) as exit_:
        main(["decode", "--dbc", str(bad), str(tmp_path / "x.log")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "bad.dbc: not a DBC cantools reads" in err and "Traceback" not in err
    with pytest.raises(ValueError, match=r"missing\.dbc"):
        Dbc.load(str(tmp_path / "missing.dbc"))


def test_audit_and_monitor_count_foreign_frames_by_protocol(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "bench.log"
    log.write_text(LOG)
    assert main(["audit", "--json", "--odrive-names", "3", str(log)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["foreign_by_protocol"] == {
        "canopen": 5,
        "odrive": 1,
        "odrive undecodable": 1,
        "unknown": 1,
    }
    assert main(["audit", str(log)]) == 0
    assert "8 foreign (canopen 5, unknown 3), " in capsys.readouterr().out
    assert main(["monitor", "--replay", str(log), "--fast", "--once", "--no-canopen"]) == 0
    assert "foreign 8 (unknown 8)" in capsys.readouterr().out
