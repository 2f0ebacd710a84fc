"""``canergy decode``/``dump``/``audit``/``monitor`` name moteus and MIT-mode frames beside
canergy's: frames encoded by the ``moteus`` package (PyPI) and by canergy's own encoders are
named with their registers or fields in units; garbage for those ids is named and counted as
undecodable, never raised."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canergy.cli import main
from canergy.devices import mit
from canergy.devices.moteus import Kind, Read, Reg, Reply, Stream, can_id, encode, extended
from canergy.inspect.candump import log_line
from canergy.inspect.named import Named
from canergy.inspect.others import Namer, protocol_of

DM4310 = mit.MODELS["DM4310"]
AK80 = mit.MODELS["AK80-9"]


def _frame(arbitration_id: int, data: bytes, fd: bool = False) -> can.Message:
    return can.Message(
        arbitration_id=arbitration_id,
        data=data,
        is_extended_id=extended(arbitration_id) if fd else False,
        is_fd=fd,
    )


def _moteus_frames() -> list[can.Message]:
    """What the moteus package sends to controller 1 (source 0), and a reply in canergy's
    encoding."""
    import moteus

    controller = moteus.Controller(id=1)
    out = []
    for command in (
        controller.make_position(
            position=math.nan, velocity=0.5, feedforward_torque=2.0, query=True
        ),
        controller.make_stop(),
        controller.make_diagnostic_write(b"conf get servo.max_power_W\n"),
    ):
        ident = can_id(command.source, command.destination, command.reply_required)
        out.append(_frame(ident, encode() if not command.data else _pad(command.data), fd=True))
    reply = encode(Reply(Kind.FLOAT, Reg.MODE, (10.0, 0.25, -1.5, 0.75, 3.0)))
    out.append(_frame(can_id(1, 0), reply, fd=True))
    out.append(_frame(can_id(1, 0), encode(Stream(True, 1, b"300\r\n")), fd=True))
    return out


def _pad(data: bytes) -> bytes:
    from canergy.devices.moteus import padded

    return padded(data)


def _log(tmp_path: Path, frames: list[can.Message]) -> Path:
    log = tmp_path / "bench.log"
    log.write_text(
        "".join(log_line(f, "can0", 1700000000 + i / 1000) for i, f in enumerate(frames))
    )
    return log


def _decoded(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], frames: list[can.Message], *flags: str
) -> list[Any]:
    assert main(["decode", "--json", *flags, str(_log(tmp_path, frames))]) == 0
    return [json.loads(line)["other"] for line in capsys.readouterr().out.splitlines()]


def test_moteus_frames_of_the_moteus_package_are_named_with_registers(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    position, stop, conf, reply, text = _decoded(
        tmp_path, capsys, _moteus_frames(), "--moteus-names", "1"
    )
    assert position["protocol"] == "moteus" and position["name"] == "command"
    assert position["node"] == 1 and position["problem"] is None
    fields = position["fields"]
    assert fields["from"] == 0 and fields["reply asked"] is True
    assert fields["mode"] == "position"
    assert fields["command_position"] == "nan"  # unset, as JSON can hold it
    assert fields["command_velocity"] == pytest.approx(0.5)
    assert fields["feedforward_torque"] == pytest.approx(2.0)
    assert "read" in fields  # the query: what the package asks back
    assert stop["fields"]["mode"] == "stopped"
    assert conf["fields"]["channel 1"] == "conf get servo.max_power_W\\n"
    assert reply["name"] == "reply" and reply["node"] == 1 and reply["fields"]["to"] == 0
    assert reply["fields"]["mode"] == "position"
    assert reply["fields"]["position"] == pytest.approx(0.25)
    assert reply["fields"]["velocity"] == pytest.approx(-1.5)
    assert reply["fields"]["torque"] == pytest.approx(0.75)
    assert reply["fields"]["q_current"] == pytest.approx(3.0)
    assert text["fields"]["channel 1"] == "300\\r\\n"
    # without the flag, none of these is named (0x100 would be CANopen's TIME)
    others = _decoded(tmp_path, capsys, _moteus_frames(), "--no-canopen")
    assert others == [None] * 5


def test_moteus_text_view(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = _log(tmp_path, _moteus_frames()[:1])
    assert main(["decode", "--moteus-names", "1", str(log)]) == 0
    out = capsys.readouterr().out
    assert "moteus: command 1  from 0  reply asked True  mode position  command_position nan" in out


def test_mit_commands_specials_and_replies_are_named_in_units(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    command = mit.encode(DM4310, p=1.0, v=-2.0, kp=10.0, kd=0.5, t=1.5).pack()
    replies = mit.pack_reply(DM4310, 1, *_codes(DM4310, 0.5, 3.0, -2.0), state=1)
    frames = [
        _frame(0x001, command),
        *(_frame(0x001, special) for special in (mit.ENTER, mit.EXIT, mit.ZERO, mit.CLEAR_ERROR)),
        _frame(0x011, replies),  # Damiao: the reply id is the motor's + 0x10
        _frame(0x001, command[:3]),  # garbage: named, not decoded
        _frame(0x101, command),  # Damiao position-velocity mode: not MIT, named so
    ]
    got = _decoded(tmp_path, capsys, frames, "--mit-names", "1", "--mit-model", "DM4310")
    assert [(g["protocol"], g["name"], g["node"]) for g in got] == [
        ("mit", "command", 1),
        ("mit", "enter", 1),
        ("mit", "exit", 1),
        ("mit", "zero", 1),
        ("mit", "clear", 1),
        ("mit", "reply", 1),
        ("mit", "command", 1),
        ("mit", "not MIT", 1),
    ]
    f = got[0]["fields"]
    steps = [float(field.span) * 2 / field.top for field in DM4310.fields()]
    for key, want, step in zip(
        ("p_rad", "v_rad_s", "kp", "kd", "t_ff_nm"), (1.0, -2.0, 10.0, 0.5, 1.5), steps, strict=True
    ):
        assert abs(f[key] - want) <= step, (key, f[key], want)
    r = got[5]["fields"]
    assert abs(r["p_rad"] - 0.5) <= steps[0] and abs(r["v_rad_s"] - 3.0) <= steps[1]
    assert abs(r["torque_nm"] + 2.0) <= steps[4] and r["state"] == 1
    assert got[6]["problem"] == "dlc 3, 8 expected" and got[6]["fields"] == {}
    assert "0x101" in got[7]["fields"]["frame"]


def _codes(model: mit.MitModel, p: float, v: float, t: float) -> tuple[int, int, int]:
    c = mit.encode(model, p, v, 0.0, 0.0, t)
    return c.p, c.v, c.t


def test_a_cubemars_reply_on_id_0_is_named_before_canopen_nmt(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    reply = mit.pack_reply(AK80, 2, *_codes(AK80, -1.0, 0.0, 4.0))
    frames = [
        _frame(0x000, reply),
        _frame(0x000, b"\x81\x05"),
        _frame(0x000, bytes([7]) + reply[1:]),
    ]
    got = _decoded(tmp_path, capsys, frames, "--mit-names", "2", "--mit-model", "AK80-9")
    assert (got[0]["name"], got[0]["node"], "state" in got[0]["fields"]) == ("reply", 2, False)
    assert abs(got[0]["fields"]["torque_nm"] - 4.0) <= 36 / 4095
    assert got[1]["protocol"] == "canopen" and got[1]["name"] == "NMT"  # two bytes: NMT
    assert got[2]["protocol"] == "canopen"  # motor 7 is none of ours: not an MIT reply


def test_two_models_on_one_bus_are_each_named_by_their_own_ranges(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--mit-names 1,2 --mit-model 1:AK80-9,2:DM4310``: the same command bytes ask an AK80-9
    for 18 N·m and a DM4310 for 10; each motor's reply on its own reply id (CubeMars 0, Damiao
    id + 0x10) is read by its own ranges; audit and monitor count them all as MIT frames."""
    command = mit.Command(0x8000, 0x800, 0, 0, 0xFFF).pack()  # the largest feed-forward torque
    frames = [
        _frame(0x001, command),
        _frame(0x002, command),
        _frame(0x000, mit.pack_reply(AK80, 1, *_codes(AK80, 1.0, 40.0, -15.0))),
        _frame(0x012, mit.pack_reply(DM4310, 2, *_codes(DM4310, 1.0, 25.0, -8.0), state=1)),
        _frame(0x302, command),  # Damiao force-position mode: reaches motor 2 outside MIT
    ]
    flags = ["--mit-names", "1,2", "--mit-model", "1:AK80-9,2:DM4310"]
    got = _decoded(tmp_path, capsys, frames, *flags)
    assert [(g["protocol"], g["name"], g["node"]) for g in got] == [
        ("mit", "command", 1),
        ("mit", "command", 2),
        ("mit", "reply", 1),
        ("mit", "reply", 2),
        ("mit", "not MIT", 2),
    ]
    assert (got[0]["fields"]["t_ff_nm"], got[1]["fields"]["t_ff_nm"]) == (18.0, 10.0)
    assert abs(got[2]["fields"]["v_rad_s"] - 40.0) <= 100 / 4095  # past the DM4310's ±30
    assert (
        abs(got[2]["fields"]["torque_nm"] + 15.0) <= 36 / 4095 and "state" not in got[2]["fields"]
    )
    assert abs(got[3]["fields"]["torque_nm"] + 8.0) <= 20 / 4095 and got[3]["fields"]["state"] == 1
    log = _log(tmp_path, frames)
    assert main(["audit", "--json", *flags, str(log)]) == 0
    assert json.loads(capsys.readouterr().out)["foreign_by_protocol"] == {"mit": 5}
    assert main(["monitor", "--replay", str(log), "--fast", "--once", *flags]) == 0
    assert "foreign 5 (mit 5)" in capsys.readouterr().out


def test_audit_and_monitor_count_undecodable_frames_apart(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    good = mit.encode(DM4310, 0.0, 0.0, 1.0, 0.1, 0.5).pack()
    frames = [
        _frame(0x005, good),  # MIT motor 5 (moteus 1's frames from 0 go to 0x001)
        _frame(0x005, good[:5]),
        *_moteus_frames()[:2],
        _frame(can_id(0, 1, True), b"\x13", fd=True),  # a read, its register cut off
    ]
    log = _log(tmp_path, frames)
    flags = ["--mit-names", "5", "--mit-model", "DM4310", "--moteus-names", "1"]
    assert main(["audit", "--json", *flags, str(log)]) == 0
    assert json.loads(capsys.readouterr().out)["foreign_by_protocol"] == {
        "mit": 1,
        "mit undecodable": 1,
        "moteus": 2,
        "moteus undecodable": 1,
    }
    assert main(["monitor", "--replay", str(log), "--fast", "--once", *flags]) == 0
    assert "foreign 5 (moteus 2, mit 1, mit undecodable 1, moteus undecodable 1)" in (
        capsys.readouterr().out
    )


def test_mit_names_without_a_model_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = _log(tmp_path, [_frame(0x001, mit.ENTER)])
    assert main(["decode", "--mit-names", "1", str(log)]) == 2
    err = capsys.readouterr().err
    assert "--mit-names needs --mit-model" in err and "Traceback" not in err
    assert main(["decode", "--mit-model", "1:DM4310", str(log)]) == 2  # names no motor listed
    err = capsys.readouterr().err
    assert "--mit-model: id 1 is not one of --mit-names's (none)" in err, err


@settings(max_examples=300, deadline=None)
@given(
    ident=st.sampled_from([0x000, 0x001, 0x011, 0x100, 0x101, 0x8001, 0x7FF, 0x7F01, 0x0100]),
    ext=st.booleans(),
    data=st.binary(max_size=64),
    model=st.sampled_from(sorted(mit.MODELS)),
)
def test_any_data_for_those_ids_is_named_or_passed_never_raised(
    ident: int, ext: bool, data: bytes, model: str
) -> None:
    namer = Namer(moteus_nodes=[1], mit_nodes=[1], mit_model=mit.MODELS[model], odrive_nodes=[8])
    named = namer.name(ident, ext, False, data)
    if named is not None:
        assert isinstance(named, Named) and named.text()
        json.dumps(named.as_json(), allow_nan=False)
        assert protocol_of(named).endswith("undecodable") == (named.problem is not None)


def test_a_moteus_read_of_many_registers_names_the_range() -> None:
    data = encode(Read(Kind.INT16, Reg.MODE, 5))
    named = Namer(moteus_nodes=[3]).name(can_id(0, 3, True), True, False, data)
    assert named is not None and named.fields["read"] == "mode..q_current (int16)"


def test_an_identifier_moteus_never_sends_is_not_named_moteus() -> None:
    """Bit 7 lies between the source and destination ids: a frame with it set (0x181, a
    CANopen TPDO of node 1) is not a moteus frame to controller 1."""
    namer = Namer(moteus_nodes=[1])
    pdo, stop = (namer.name(i, False, False, b"\x01\x00\x00") for i in (0x181, 0x001))
    assert pdo is not None and pdo.protocol == "canopen"
    assert stop is not None and stop.protocol == "moteus"
