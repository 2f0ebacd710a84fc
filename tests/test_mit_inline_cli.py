"""``canergy inline``'s checks before any bus is opened: each names the flag at fault."""

from __future__ import annotations

import pytest

from canergy.cli import build_parser, main
from canergy.cli.inline import motors

BUSES = ["-i", "virtual", "-c", "motors", "--app-interface", "virtual", "--app-channel", "app"]
TWO = ["--mit", "1,2", "--mit-nodes", "11,12"]


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--mit", "1,2", "--mit-nodes", "11", "--mit-model", "DM4310"], "--mit names 2 motors"),
        (["--mit", "1", "--mit-nodes", "11", "--mit-model", "AK80-9"], "give --mit-resistance"),
        (
            [
                *("--mit", "1", "--mit-nodes", "11", "--mit-model", "DM4310"),
                *("--mit-max-torque", "1", "--mit-max-power", "10"),
            ],
            "--mit-max-torque or --mit-max-power",
        ),
        (
            ["--mit", "1", "--mit-nodes", "11", "--mit-model", "DM4310", "--app-channel", "motors"],
            "name the same bus",
        ),
        ([*TWO, "--mit-model", "1:AK80-9,3:DM4310"], "--mit-model: id 3 is not one of --mit's"),
        ([*TWO, "--mit-model", "1:DM4310"], "--mit-model: no model for motor 2"),
        ([*TWO, "--mit-model", "1:AK80-9,2:DM4310"], "(motor 1): give --mit-resistance"),
        (
            [*TWO, "--mit-model", "1:AK80-9,2:DM4310", "--mit-resistance", "0.2"],
            "--mit-resistance: the motors are of more than one model",
        ),
        (
            [*TWO, "--mit-model", "AK80-9", "--mit-resistance", "3:0.2"],
            "--mit-resistance: id 3 is not one of --mit's",
        ),
        (  # a DM4310's replies go out on its id + 0x10: motor 17's commands
            ["--mit", "1,17", "--mit-nodes", "11,12", "--mit-model", "DM4310"],
            "--mit: MIT motor 1's replies go out on 0x011, motor 17's command identifier",
        ),
    ],
)
def test_bad_combinations_are_refused_naming_the_flag(
    extra: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["inline", *BUSES, *extra]) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("AK80", "unknown model 'AK80': one of AK70-10, AK80-9, DM4310"),
        ("1:DM4310,1:AK80-9", "id 1 named twice"),
        ("1-2:DM4310,2:AK80-9", "id 2 named twice"),
        ("DM4310,AK80-9", "one plain value at most"),
        ("0:DM4310", "bad node range '0'"),
        ("x:DM4310", "bad node list 'x'"),
        ("1=DM4310", "unknown model '1=DM4310'"),
        ("", "unknown model ''"),
    ],
)
@pytest.mark.parametrize("command", ["inline", "decode"])
def test_bad_model_lists_are_refused_in_one_line_naming_the_flag(
    command: str, value: str, message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    rest = [*BUSES, *TWO] if command == "inline" else ["--mit-names", "1,2", "-"]
    with pytest.raises(SystemExit) as ended:
        main([command, *rest, "--mit-model", value])
    err = capsys.readouterr().err
    assert ended.value.code == 2 and "Traceback" not in err
    (line,) = [e for e in err.splitlines() if "error:" in e]
    assert "argument --mit-model: " in line and message in line, line


def test_a_model_per_id_and_a_plain_one_for_the_rest() -> None:
    """``3:AK80-9,DM4310``: motor 3 an AK80-9, the others DM4310; a resistance per id for the
    model the table has none for, the table's for the others."""
    argv = ["inline", *BUSES, "--mit", "1-3", "--mit-nodes", "11-13"]
    argv += ["--mit-model", "3:AK80-9,DM4310", "--mit-resistance", "3:0.2"]
    wanted = motors(build_parser().parse_args(argv))
    got = [(m.motor_id, m.node, m.model, m.resistance) for m in wanted]
    assert got == [(1, 11, "DM4310", None), (2, 12, "DM4310", None), (3, 13, "AK80-9", 0.2)]


def test_buses_left_to_python_cans_configuration_are_not_an_error() -> None:
    """Without -c or --app-channel (python-can's configuration names them) the flags still
    describe the motors (the hypothesis fuzz met an AttributeError here)."""
    argv = ["inline", "-i", "virtual", "--mit", "1", "--mit-nodes", "11", "--mit-model", "DM4310"]
    (motor,) = motors(build_parser().parse_args(argv))
    assert (motor.motor_id, motor.node, motor.model) == (1, 11, "DM4310")


def test_gates_refuse_a_motor_whose_replies_are_another_motors_commands() -> None:
    """In the library too (``MitBus``, the supervisor's gates): motor 1's replies on 0x011
    would reach motor 17 as a command its gate never clamped."""
    from canergy.live.devices.mit_bus import MitMotor
    from canergy.live.devices.mit_gates import MitGates

    with pytest.raises(ValueError, match="motor 17's command identifier"):
        MitGates([MitMotor(1, node=11), MitMotor(17, node=12)], 0)
    with pytest.raises(ValueError, match="0x005, its own command identifier"):
        MitGates([MitMotor(5, node=11, master_id=5)], 0)
    assert set(MitGates([MitMotor(1, node=11), MitMotor(18, node=12)], 0).gates) == {1, 18}
