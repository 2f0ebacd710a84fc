"""Duration and energy options at the command line: units, defaults and one-line errors."""

from __future__ import annotations

import argparse
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from canergy.argtypes import duration, milliseconds
from canergy.cli import build_parser
from firmware_model.__main__ import build_parser as firmware_parser

SUPERVISOR = ["supervisor", "--nodes", "1"]
GRANT = ["grant", "--node", "1", "--amount", "1J"]
FIRMWARE = ["--node", "1", "--nv", "x.nv"]
SIMULATE = ["simulate", "--out", "sim"]

OPTIONS: list[tuple[Callable[[], argparse.ArgumentParser], list[str], str]] = [
    *(
        (build_parser, SUPERVISOR, o)
        for o in (
            "--response-timeout",
            "--stop-timeout",
            "--lost-after",
            "--status-period",
            "--heartbeat-timeout",
        )
    ),
    *((build_parser, GRANT, o) for o in ("--timeout", "--response-timeout", "--stop-timeout")),
    *(
        (firmware_parser, FIRMWARE, o)
        for o in ("--tick", "--telemetry-period", "--response-timeout", "--status-period")
    ),
    *(
        (build_parser, SIMULATE, o)
        for o in ("--duration", "--delay-ms", "--jitter-ms", "--timeout-ms", "--return-every")
    ),
    (build_parser, ["demo"], "--duration"),
]


def _error(
    parser: argparse.ArgumentParser, argv: list[str], capsys: pytest.CaptureFixture[str]
) -> str:
    with pytest.raises(SystemExit) as exc:
        parser.parse_args(argv)
    assert exc.value.code == 2
    return capsys.readouterr().err


@pytest.mark.parametrize("value", ["inf", "nan", "-1", "1e999999", "5 parsecs", ""])
@pytest.mark.parametrize(("make", "base", "option"), OPTIONS)
def test_bad_durations_exit_2_naming_the_option(
    make: Callable[[], argparse.ArgumentParser],
    base: list[str],
    option: str,
    value: str,
    capsys: pytest.CaptureFixture[str],
) -> None:
    err = _error(make(), [*base, f"{option}={value}"], capsys)
    errors = [line for line in err.splitlines() if "error:" in line]
    assert len(errors) == 1 and f"argument {option}" in errors[0], err
    assert "Traceback" not in err


@pytest.mark.parametrize(("make", "base", "option"), OPTIONS)
def test_durations_take_units(
    make: Callable[[], argparse.ArgumentParser], base: list[str], option: str
) -> None:
    args = make().parse_args([*base, option, "1.5s"])
    assert getattr(args, option[2:].replace("-", "_")) == 1_500_000


def test_zero_is_rejected_where_a_duration_must_be_positive() -> None:
    for parse in (duration, milliseconds):
        with pytest.raises(argparse.ArgumentTypeError, match="more than 0"):
            parse("0ms")
    assert build_parser().parse_args([*SIMULATE, "--return-every", "0"]).return_every == 0


def test_defaults_keep_their_values() -> None:
    sup = build_parser().parse_args(SUPERVISOR)
    assert (sup.response_timeout, sup.stop_timeout, sup.lost_after) == (
        50_000,
        5_000_000,
        3_000_000,
    )
    assert (sup.status_period, sup.heartbeat_timeout) == (1_000_000, 3_000_000)
    assert build_parser().parse_args(GRANT).timeout == 10_000_000
    fw = firmware_parser().parse_args(FIRMWARE)
    assert (fw.tick, fw.telemetry_period, fw.response_timeout, fw.status_period) == (
        100_000,
        1_000_000,
        100_000,
        1_000_000,
    )
    sim = build_parser().parse_args(SIMULATE)
    assert (sim.duration, sim.return_every, sim.delay_ms) == (60_000_000, 5_000_000, None)
    assert build_parser().parse_args(["demo"]).duration is None  # per topology (300s, tree 60s)
    assert build_parser().parse_args(["demo", "--duration", "2min"]).duration == 120_000_000
    assert build_parser().parse_args([*SIMULATE, "--delay-ms", "250"]).delay_ms == 250_000


def test_help_shows_defaults_with_units(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        build_parser().parse_args(["supervisor", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "(default 50ms;" in out and "(default 3s;" in out and "at most a week" in out


@pytest.mark.parametrize("value", ["1e400J", "1e999999J", "1e900000J"])
def test_huge_energies_are_one_line_errors(value: str, capsys: pytest.CaptureFixture[str]) -> None:
    err = _error(build_parser(), [*SUPERVISOR, "--initial", value], capsys)
    assert "argument --initial" in err and "too large (at most 1000000000 J)" in err


@pytest.mark.parametrize(
    "argv",
    [
        ["-m", "canergy", *SUPERVISOR, "--response-timeout", "inf"],
        ["-m", "canergy", *GRANT, "--timeout", "nan"],
        ["-m", "firmware_model", *FIRMWARE, "--tick", "-1"],
    ],
)
def test_bad_duration_in_a_real_process(argv: list[str]) -> None:
    root = Path(__file__).parent.parent
    run = subprocess.run([sys.executable, *argv], cwd=root, capture_output=True, text=True)
    assert run.returncode == 2 and "Traceback" not in run.stderr
    assert f"argument {argv[-2]}" in run.stderr.splitlines()[-1]
