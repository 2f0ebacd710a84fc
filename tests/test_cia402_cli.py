"""``canergy supervisor --cia402`` on the command line: a metering mode must be chosen, each mode
asks for what it needs in one line, the old sampled names say what they became, and a sampled
mode warns that it guarantees nothing (before any bus is opened)."""

from __future__ import annotations

from pathlib import Path

import pytest

from canergy.cli import main

BASE = ("supervisor", "-i", "virtual", "-c", "cia402-cli", "--cia402", "10", "--initial", "1J")
LIMITS = ("--cia402-max-torque", "265", "--cia402-max-current", "265", "--cia402-max-speed", "9")


def run(capsys: pytest.CaptureFixture[str], tmp_path: Path, *flags: str) -> tuple[int, str]:
    try:
        code = main([*BASE, "--state", str(tmp_path / "s.json"), *flags])
    except SystemExit as exc:  # argparse's own refusals
        code = int(str(exc.code))
    return code, capsys.readouterr().err


@pytest.mark.parametrize(
    ("flags", "said"),
    [
        ((), "--cia402 needs --cia402-meter MODE (counter, envelope, sampled-mechanical"),
        (("--cia402-meter", "envelope"), "needs --cia402-max-torque, --cia402-max-current"),
        (("--cia402-meter", "counter", *LIMITS), "needs --cia402-counter [NODE:]INDEX"),
        (("--cia402-meter", "sampled-electrical"), "needs --cia402-bus-current INDEX"),
        (
            ("--cia402-meter", "counter", "--cia402-counter", "10:0x2100", *LIMITS),
            "--cia402-counter node 10 is also a node or drive id",
        ),
        (("--cia402-meter", "mechanical"), "'mechanical' is now 'sampled-mechanical'"),
        (("--cia402-meter", "counter", "--cia402-counter", "0x20"), "index 0x1000-0xFFFF"),
        (("--cia402-meter", "counter", "--cia402-counter", "x:y"), "[NODE:]INDEX[.SUB]"),
        (("--cia402-counter-bits", "12"), "8, 16, 32 or 64 bits"),
        (("--cia402-max-torque", "0"), "--cia402-max-torque"),
    ],
)
def test_what_a_mode_lacks_is_said_in_one_line(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, flags: tuple[str, ...], said: str
) -> None:
    code, err = run(capsys, tmp_path, *flags)
    assert code == 2 and said in err, err
    assert len(err.strip().splitlines()[-1]) < 300  # one readable line, no traceback
    assert "Traceback" not in err


def test_a_power_meter_node_meters_one_drive(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    flags = ("--cia402-meter", "counter", "--cia402-counter", "20:0x2100", *LIMITS)
    code = main([*BASE[:-4], "--cia402", "10-11", "--initial", "1J", *flags])
    assert code == 2 and "meters one drive" in capsys.readouterr().err


def test_a_sampled_mode_warns_at_start_that_it_guarantees_nothing(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    from canergy.cli.shared.cia402 import SAMPLED_WARNING

    code, err = run(
        capsys,
        tmp_path,
        "--cia402-meter",
        "sampled-mechanical",
        "--cia402-eds",
        str(tmp_path / "missing.eds"),  # refused right after the warning: no bus needed
    )
    assert code == 2
    assert "not a usable EDS" in err
    assert SAMPLED_WARNING.format(mode="sampled-mechanical") in err
    code, err = run(
        capsys, tmp_path, "--cia402-meter", "envelope", *LIMITS, "--cia402-eds", "missing.eds"
    )
    assert code == 2 and "warning" not in err  # the sound modes have nothing to warn of


def test_a_reach_below_the_limit_the_guard_writes_is_refused(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """The reach is what a write behind the guard is charged at: never less than what the
    guard itself writes."""
    flags = ("--cia402-meter", "envelope", *LIMITS, "--cia402-reach-torque", "100")
    code, err = run(capsys, tmp_path, *flags)
    assert code == 2 and "--cia402-reach-torque 100 is below --cia402-max-torque" in err, err
