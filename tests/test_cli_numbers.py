"""Every numeric option of every command is bounded at parse time (issue 13): ``inf``, ``nan``,
huge and out-of-range values are one-line argparse errors naming the option, exit status 2,
before any work starts."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from canergy.argtypes import COUNT_MAX, SEED_MAX, bounded_int, max_processes
from canergy.cli import build_parser, main
from canergy.cli.check import CHECK_BOUND_MAX
from canergy.cli.demo import DEMO_TRANSACTIONS_MAX
from canergy.cli.shared.sim import LOSS_POINTS_MAX
from canergy.cli.sweep import SEEDS_MAX
from canergy.inspect.captures import read_text
from firmware_model.__main__ import build_parser as firmware_parser

ROOT = Path(__file__).parent.parent
Parser = Callable[[], argparse.ArgumentParser]


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    (sub,) = (a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def _typed_options() -> list[tuple[str, str]]:
    """(command, option) for every option whose value goes through a type function: all of
    them with a number among what they take (paths and free text such as --channel are not)."""
    parsers = {**_subparsers(), "firmware_model": firmware_parser()}
    found = []
    for name, parser in parsers.items():
        for action in parser._actions:
            if action.option_strings and action.type not in (None, str, Path):
                found.append((name, max(action.option_strings, key=len)))
    return found


def _parse(command: str, argv: list[str]) -> argparse.Namespace:
    if command == "firmware_model":
        return firmware_parser().parse_args(argv)
    return build_parser().parse_args([command, *argv])


def _refused(command: str, argv: list[str], option: str, capsys: pytest.CaptureFixture[str]) -> str:
    """The one error line of a parse that must fail naming ``option``."""
    with pytest.raises(SystemExit) as exc:
        _parse(command, argv)
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if "error:" in line]
    assert exc.value.code == 2 and len(errors) == 1, err
    assert f"argument {option}" in errors[0] or f"/{option}:" in errors[0], err
    assert "Traceback" not in err
    return errors[0]


def test_every_numeric_option_is_found() -> None:
    options = set(_typed_options())
    for case in [
        ("check", "--transactions"),
        ("check", "--units"),
        ("sweep", "--processes"),
        ("demo", "--seed"),
        ("simulate", "--seed"),
        ("sweep", "--first-seed"),
        ("dbc", "--id-base"),
        ("decode", "--id-base"),
        ("dump", "--count"),
        ("dump", "--bitrate"),
        ("firmware_model", "--crash-after"),
        ("firmware_model", "--data-bitrate"),
        ("supervisor", "--retries"),
    ]:
        assert case in options


@pytest.mark.parametrize("value", ["inf", "-inf", "nan", "1e999", "9" * 30, "-1", "1" * 5000])
@pytest.mark.parametrize(("command", "option"), _typed_options())
def test_no_numeric_option_takes_inf_nan_or_huge_values(
    command: str, option: str, value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    line = _refused(command, [f"{option}={value}"], option, capsys)
    assert len(line) < 200  # one short line, whatever was typed


# the reproductions, each of which overflowed, grew without end or never answered
@pytest.mark.parametrize(
    ("command", "option", "value"),
    [
        ("check", "--transactions", "99999999999999999999999"),
        ("check", "--units", "99999999999999999999"),
        ("sweep", "--processes", "99999999999"),
    ],
)
def test_the_reported_values_are_refused(
    command: str, option: str, value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    _refused(command, [option, value], option, capsys)


UPPER_BOUNDS: list[tuple[str, list[str], str, int]] = [
    *(
        ("check", [], option, CHECK_BOUND_MAX)
        for option in (
            "--transactions",
            "--losses",
            "--duplicates",
            "--power-losses",
            "--in-flight",
            "--units",
            "--retries",
            "--timeouts",
        )
    ),
    ("check", [], "--clients", 8),
    ("check", [], "--max-states", COUNT_MAX),
    ("demo", [], "--transactions", DEMO_TRANSACTIONS_MAX),
    ("demo", [], "--seed", SEED_MAX),
    ("demo", [], "--resets", 100),
    ("simulate", ["--out", "x"], "--seed", SEED_MAX),
    ("sweep", ["--out", "x"], "--first-seed", SEED_MAX),
    ("sweep", ["--out", "x"], "--seeds", SEEDS_MAX),
    ("sweep", ["--out", "x"], "--processes", max_processes()),
    ("dump", [], "--count", COUNT_MAX),
    ("dump", [], "--bitrate", 20_000_000),
    ("supervisor", ["--nodes", "1"], "--data-bitrate", 20_000_000),
    ("firmware_model", ["--node", "1", "--nv", "x.nv"], "--crash-after", COUNT_MAX),
    ("firmware_model", ["--node", "1", "--nv", "x.nv"], "--bitrate", 20_000_000),
]


@pytest.mark.parametrize(("command", "base", "option", "largest"), UPPER_BOUNDS)
def test_integer_options_have_an_upper_bound(
    command: str, base: list[str], option: str, largest: int, capsys: pytest.CaptureFixture[str]
) -> None:
    args = _parse(command, [*base, option, str(largest)])
    assert getattr(args, option[2:].replace("-", "_")) == largest
    line = _refused(command, [*base, option, str(largest + 1)], option, capsys)
    assert "outside" in line and str(largest) in line


def test_process_count_follows_the_machine() -> None:
    assert 1 <= max_processes() <= 256


@pytest.mark.parametrize("command", ["dbc", "decode", "audit", "dump", "supervisor"])
@pytest.mark.parametrize("value", ["0x0CE00001", "0x20000000", "0x1FFFFFFF", "-4096"])
def test_id_base_is_a_29_bit_block_at_parse_time(
    command: str, value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    base = {"audit": ["cap.log"], "supervisor": ["--nodes", "1"]}.get(command, [])
    _refused(command, [*base, f"--id-base={value}"], "--id-base", capsys)
    assert _parse(command, [*base, "--id-base", "0x1FFFF000"]).id_base == 0x1FFFF000


def test_firmware_id_base_is_checked_at_parse_time(capsys: pytest.CaptureFixture[str]) -> None:
    base = ["--node", "1", "--nv", "x.nv"]
    _refused("firmware_model", [*base, "--id-base", "0x0CE00010"], "--id-base", capsys)


@pytest.mark.parametrize("value", ["nan", "0,nan", "inf", "0,0.1,-inf", "1e999"])
def test_sweep_loss_rates_are_finite(value: str, capsys: pytest.CaptureFixture[str]) -> None:
    _refused("sweep", ["--out", "x", f"--loss={value}"], "--loss", capsys)


def test_sweep_takes_a_bounded_number_of_loss_rates(capsys: pytest.CaptureFixture[str]) -> None:
    many = ",".join(["0.1"] * LOSS_POINTS_MAX)
    assert len(_parse("sweep", ["--out", "x", "--loss", many]).loss) == LOSS_POINTS_MAX
    _refused("sweep", ["--out", "x", "--loss", many + ",0.2"], "--loss", capsys)


def test_seeds_run_to_2_32_at_most(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    argv = ["sweep", "--first-seed", str(SEED_MAX), "--seeds", "2", "--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--first-seed" in err and "--seeds" in err
    assert not out.exists()


@pytest.mark.parametrize("value", ["-1", "-5"])
def test_seeds_are_not_negative(value: str, capsys: pytest.CaptureFixture[str]) -> None:
    _refused("demo", [f"--seed={value}"], "--seed", capsys)


def test_bounded_int_needs_an_upper_bound_and_quotes_little() -> None:
    parse = bounded_int(0, 10)
    assert parse("0x0a") == 10
    with pytest.raises(argparse.ArgumentTypeError, match=r"outside 0\.\.10"):
        parse("11")
    with pytest.raises(argparse.ArgumentTypeError) as exc:
        parse("7" * 100_000)
    assert len(str(exc.value)) < 80


def test_a_capture_timestamp_beyond_float_range_is_garbage() -> None:
    line = f"({'9' * 400}.0) vcan0 0CE00901#0B0100"
    bad: list[str] = []
    assert list(read_text([line], lambda n, text, why: bad.append(why))) == []
    assert bad == ["timestamp out of range"]


def test_decode_json_never_prints_infinity(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    capture = tmp_path / "cap.log"
    capture.write_text(f"({'9' * 400}.0) vcan0 0CE00901#0B0100\n(1.5) vcan0 0CE00901#0B0100\n")
    assert main(["decode", "--json", str(capture)]) == 0
    (frame,) = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert frame["timestamp"] == 1.5


@pytest.mark.parametrize(
    "argv",
    [
        ["-m", "canergy", "check", "--transactions", "99999999999999999999999"],
        ["-m", "canergy", "check", "--units", "99999999999999999999"],
        ["-m", "canergy", "sweep", "--out", "never-written", "--processes", "99999999999"],
        ["-m", "firmware_model", "--node", "1", "--nv", "x.nv", "--crash-after", "1e999"],
    ],
)
def test_in_a_real_process(argv: list[str], tmp_path: Path) -> None:
    run = subprocess.run(
        [sys.executable, *argv], cwd=tmp_path, capture_output=True, text=True, timeout=60
    )
    assert run.returncode == 2 and "Traceback" not in run.stderr
    assert f"argument {argv[-2]}" in run.stderr.splitlines()[-1]
    assert list(tmp_path.iterdir()) == []
