"""``canergy bench`` with bus flags: the flags handed to the node and SDO server processes, and
clear refusals. (The run itself is tested on vcan0: tests/test_vcan_bench.py.)"""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from canergy.bench import run
from canergy.bench.on_bus import BusTarget, node_commands
from canergy.cli import main
from canergy.cli.bench import bus_target
from canergy.cli.shared.bus_flags import add_bus_flags, bus_argv


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_bus_flags(parser)
    return parser.parse_args(argv)


def _target(argv: list[str]) -> BusTarget:
    return bus_target(_parse(argv))


@pytest.mark.parametrize(
    "argv",
    [
        ["-i", "socketcan", "-c", "vcan0"],
        ["-i", "pcan", "-c", "PCAN_USBBUS1", "-b", "500000", "--id-base", "0x1000000"],
        ["-i", "socketcan", "-c", "can0", "--fd", "--data-bitrate", "2000000"],
        ["-i", "zenoh", "-c", "lab", "--bus-kwargs", "connect=tcp/127.0.0.1:7447", "n=3"],
    ],
)
def test_bus_flags_reach_the_other_processes_unchanged(argv: list[str]) -> None:
    args = _parse(argv)
    again = _parse(bus_argv(args))
    assert vars(again) == vars(args)


def test_refusals_name_the_flag() -> None:
    with pytest.raises(ValueError, match="virtual bus does not cross processes"):
        bus_argv(_parse(["-i", "virtual", "-c", "x"]))
    with pytest.raises(ValueError, match="--timing"):
        bus_argv(
            _parse(
                [
                    "-i",
                    "socketcan",
                    "-c",
                    "can0",
                    "--timing",
                    "f_clock=8000000",
                    "brp=1",
                    "tseg1=5",
                    "tseg2=2",
                    "sjw=1",
                    "nof_samples=1",
                ]
            )
        )
    with pytest.raises(ValueError, match="SocketCAN only"):
        node_commands(_target(["-i", "pcan", "-c", "x"]), 2, Path("/tmp"), Path("/bin/true"))


def test_c_nodes_are_one_process_per_node() -> None:
    target = _target(["-i", "socketcan", "-c", "vcan0", "--id-base", "0x1000000"])
    commands = node_commands(target, 3, Path("/nv"), Path("/opt/canergy-node"))
    assert [c[c.index("--node") + 1] for c in commands] == ["1", "2", "3"]
    assert all(c[c.index("--id-base") + 1] == "0x01000000" for c in commands)
    assert commands[2][-2:] == ["--nv", "/nv/3.nv"]


def test_the_python_emulator_gets_the_node_range_and_the_bus(tmp_path: Path) -> None:
    target = _target(["-i", "socketcan", "-c", "vcan0"])
    (command,) = node_commands(target, 16, tmp_path, None)
    assert command[1:3] == ["-m", "firmware_model"]
    assert command[command.index("--nodes") + 1] == "1-16"
    assert command[command.index("-c") + 1] == "vcan0"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["-i", "virtual", "-c", "x"], "does not cross processes"),
        (["-i", "socketcan", "-c", "vcan0", "--c-node", "/no/such/node"], "no such program"),
    ],
)
def test_cli_errors_are_clear(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bench", *argv]) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("value", ["0", "128", "1,x", ""])
def test_bad_node_counts_are_refused(value: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["bench", "-i", "socketcan", "-c", "vcan0", "--nodes", value])
    assert exc.value.code == 2
    assert "--nodes" in capsys.readouterr().err


def _row(nodes: int, cpu: float, *, state_file: bool = False, p50: float = 1.0) -> dict:
    return {
        "nodes": nodes,
        "supervisor_cpu_us_per_frame": cpu,
        "state_file": state_file,
        "latency_p50_ms": p50,
    }


def test_the_cpu_target_is_judged_at_its_node_counts_when_they_ran() -> None:
    # one node pays a loop pass per frame: its row is shown, not judged, when 16 ran too
    rows = [
        _row(1, 90.0),
        _row(16, 30.0),
        _row(1, 95.0, state_file=True),
        _row(16, 40.0, state_file=True),
    ]
    headroom = run.supervisor_headroom(rows)
    assert headroom["by_nodes"] == {"16": 30.0} and headroom["with_state_file"] == {"16": 40.0}
    assert headroom["supervisor_cpu_us_per_frame"] == 30.0
    only_small = run.supervisor_headroom([_row(1, 90.0), _row(4, 50.0)])  # none of 16, 127
    assert only_small["supervisor_cpu_us_per_frame"] == 90.0
    assert set(only_small["by_nodes"]) == {"1", "4"}


def test_the_latency_ratio_takes_the_one_node_row_wherever_it_is() -> None:
    sdo = {"latency_p50_ms": 0.5}
    rows = [
        _row(16, 30.0, p50=8.0),
        _row(1, 60.0, p50=1.5),
        _row(1, 70.0, state_file=True, p50=2.0),
    ]
    assert run.latency_ratio(rows, sdo) == 3.0
    assert run.latency_ratio(rows[:1], sdo) is None  # no 1-node row ran


def test_core_names_which_supervisor_cores_run(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from canergy.ccore import supervisor as ccore
    from canergy.cli.bench import _cores

    monkeypatch.setattr(ccore, "missing", lambda: None)
    assert _cores("both") == ("python", "c") and _cores("c") == ("c",)
    assert _cores("python") == ("python",)
    monkeypatch.setattr(ccore, "missing", lambda: "not built here")
    assert _cores("both") == ("python",)
    assert "the Python core only: not built here" in capsys.readouterr().err
    with pytest.raises(ValueError, match="--core c: not built here"):
        _cores("c")
    assert main(["bench", "-i", "socketcan", "-c", "vcan0", "--core", "c"]) == 2
    assert "--core c: not built here" in capsys.readouterr().err
