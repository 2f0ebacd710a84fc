"""``canergy bench`` on real SocketCAN (vcan0): the supervisor in the bench process, the nodes
in processes of their own (the Python emulator, then the C node), the SDO baseline against a
server process. Figures inside user-mode Linux are not speed figures: only the run's shape and
its counts are checked here."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from support.firmware_build import c_node as c_node  # the fixture: makes canergy-node

pytestmark = pytest.mark.vcan

BENCH = [sys.executable, "-m", "canergy", "bench", "-i", "socketcan", "-c", "vcan0"]


def _bench(tmp_path: Path, *extra: str) -> dict[str, object]:
    out = tmp_path / "bench.json"
    argv = [*BENCH, "--nodes", "1,3", "--duration", "1.5s", "--writes", "100", "--json", str(out)]
    run = subprocess.run([*argv, *extra], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert "live stack on socketcan vcan0" in run.stdout
    report: dict[str, object] = json.loads(out.read_text())
    return report


def _check(report: dict[str, object]) -> None:
    """Both cores' rows (the C core's under ``c_core``: ``scripts/test`` builds it), each with
    its own latency ratio over the one SDO baseline."""
    try:
        c_core = report["c_core"]
        assert isinstance(c_core, dict), "no C core rows"
        _check_shape(report)
        _check_shape({**report, **c_core})
        assert [row["core"] for row in report["live"]] == ["python"] * 4  # type: ignore[attr-defined]
        assert [row["core"] for row in c_core["live"]] == ["c"] * 4
        assert isinstance(report["c_vs_python"], dict)
    except AssertionError as exc:  # show the whole report: a run in UML is hard to repeat
        raise AssertionError(f"{exc}\n{json.dumps(report, indent=1)[:4000]}") from exc


def _check_shape(report: dict[str, object]) -> None:
    rows = report["live"]
    assert isinstance(rows, list) and [row["nodes"] for row in rows] == [1, 3, 1, 3]
    assert [row["state_file"] for row in rows] == [False, False, True, True]
    for row in rows:
        assert row["transactions"] > 0
        assert (row["saves_per_tx"] > 0) == row["state_file"]  # books saved, once per pass
        # INTENTION, ACK, COMMIT, COMMITTED, re-sends; a transaction open at either end of the
        # window is counted with only some of its frames
        assert 3.8 <= row["frames_per_tx"] < 5
        assert 0 < row["latency_p50_ms"] <= row["latency_p99_ms"]
        assert row["supervisor_cpu_us_per_frame"] > 0 and row["nodes_cpu_us_per_frame"] > 0
        assert 0 < row["bus_cpu_us_per_frame"] < row["supervisor_cpu_us_per_frame"]
        profile = row["latency_profile"]  # one node: the supervisor's turns; the nodes unseen
        if row["nodes"] == 1:
            assert profile["supervisor_turn_us"] > 0 and profile["nodes_turn_us"] is None
            assert 0 < profile["nodes_and_bus_us"] < 1e3 * row["latency_p50_ms"]
        else:
            assert profile is None
    sdo = report["sdo"]
    assert isinstance(sdo, dict) and sdo["writes"] == 100 and sdo["latency_p50_ms"] > 0
    assert isinstance(report["latency_ratio_vs_sdo"], float)
    headroom = report["headroom"]
    assert isinstance(headroom, dict) and headroom["supervisor_cpu_us_per_frame"] > 0
    assert set(headroom["with_state_file"]) == {"1", "3"}


def test_bench_on_vcan0_with_emulator_processes(tmp_path: Path) -> None:
    report = _bench(tmp_path)
    assert report["nodes_by"] == "python -m firmware_model"
    _check(report)


def test_bench_on_vcan0_with_c_nodes(tmp_path: Path, c_node: Path) -> None:
    report = _bench(tmp_path, "--c-node", str(c_node))
    assert report["nodes_by"] == "C node processes"
    _check(report)
    processes = [row["node_processes"] for row in report["live"]]  # type: ignore[attr-defined]
    assert processes == [1, 3, 1, 3]
