"""`canergy bench --quick`: a smoke run that checks the report's shape, never a speed."""

from __future__ import annotations

import json
import os
import statistics
from pathlib import Path

import pytest

from canergy.bench import alone, live
from canergy.cli import main
from canergy.frame_bits import frame_bits
from firmware_model.nvstore import RECORD_SIZE, SLOT_SIZE


def test_frame_bits_match_the_textbook_figures() -> None:
    assert frame_bits(8, extended=False, worst_stuffing=False) == 111
    assert frame_bits(8, extended=False, worst_stuffing=True) == 135
    assert frame_bits(0, extended=True, worst_stuffing=False) == 67


def test_quick_bench_runs_every_comparison(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "bench.json"
    assert main(["bench", "--quick", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert {"codec", "core", "live", "sdo", "wire", "headroom", "memory", "code"} <= set(report)
    assert report["code"]["version"]  # and the commit, run from a checkout (test_bench_code)
    assert len(report["codec"]["rows"]) == 11
    assert [r["core"] for r in report["core"]] == ["python"] * 4 + ["c"] * 4  # both cores
    assert all(r["tx_per_s"] > 0 for r in report["core"])
    rows = report["live"]  # then 16 and 127 again with the supervisor's books in a state file
    assert [(row["nodes"], row["state_file"]) for row in rows] == [
        (1, False),
        (16, False),
        (127, False),
        (16, True),
        (127, True),
    ]
    assert sum(row["transactions"] for row in rows) > 0
    for row in rows:  # measured apart: the supervisor's loop thread, the nodes'
        assert row["supervisor_cpu_us_per_frame"] > 0 and row["nodes_cpu_us_per_frame"] > 0
        assert 0 < row["bus_cpu_us_per_frame"] < row["supervisor_cpu_us_per_frame"]
        assert (row["saves_per_tx"] > 0) == row["state_file"]
    headroom = report["headroom"]
    worst = max(row["supervisor_cpu_us_per_frame"] for row in rows[1:3])
    assert headroom["supervisor_cpu_us_per_frame"] == worst
    for key in ("alone", "alone_with_state_file", "alone_frame_by_frame"):  # one thread
        assert set(headroom[key]) == {"16", "127"} and min(headroom[key].values()) > 0
    assert headroom["with_state_file"] == {
        str(row["nodes"]): row["supervisor_cpu_us_per_frame"] for row in rows[3:]
    }
    assert headroom["met"] == (worst <= headroom["target_us_per_frame"])
    if not headroom["met"]:  # a miss comes with the profile of the supervisor's loop thread
        own = ("service.py", "frame_path.py", "frame_answers.py", "supervisor.py")
        profile = headroom["profile_16_nodes"]
        assert any(f["function"].startswith(own) for f in profile), profile
    rounds = report["latency_rounds"]  # 1-node transactions and SDO writes in turns
    assert len(rounds) == 3
    for r in rounds:
        assert r["ratio"] == r["canergy_p50_ms"] / r["sdo_p50_ms"] > 0
    assert report["latency_ratio_vs_sdo"] == statistics.median(r["ratio"] for r in rounds)
    for r in rounds:  # the floor: two bare python-can round trips, in the same turns
        assert r["floor_ratio"] == r["bare_round_trips_p50_ms"] / r["sdo_p50_ms"] > 0
    assert report["latency_floor_vs_sdo"] == statistics.median(r["floor_ratio"] for r in rounds)
    profile = rows[0]["latency_profile"]  # where the 1-node transaction's time goes
    assert (profile is None) == (rows[0]["latency_p50_ms"] is None)  # none in a short window
    assert all(row["latency_profile"] is None for row in rows[1:])  # turns: one node only
    out_text = capsys.readouterr().out
    assert "two bare python-can round trips on this bus" in out_text
    assert f"code: canergy {report['code']['version']}" in out_text
    if profile is not None:
        assert profile["supervisor_turn_us"] > 0 and profile["nodes_turn_us"] > 0
        assert f"supervisor 2 x {profile['supervisor_turn_us']:.0f} us" in out_text
    assert report["skipped"] == []  # the emulator is importable here
    assert report["memory"]["client_nv_record_bytes"] <= 32
    tree = report["tree"]
    assert tree["tree"]["nodes"] > tree["baseline"]["nodes"] and tree["tree"]["passive"]
    assert tree["tree"]["transactions"] > 0 and tree["bytes_per_added_node"] > 0
    monitor = report["monitor"]  # a lossless virtual bus: the monitor counts every frame
    assert monitor["frames_sent"] == monitor["frames_counted"] == monitor["model_frames"] == 500
    assert "quick smoke run" in out_text
    c_core = report["c_core"]  # the live stack again on the C core, compared in the same run
    assert [(row["nodes"], row["core"]) for row in c_core["live"]] == [
        (n, "c") for n in (1, 16, 127, 16, 127)
    ] and all(row["core"] == "python" for row in rows)
    ratios = report["c_vs_python"]
    for key in ("by_nodes", "alone", "alone_frame_by_frame"):
        for n, x in ratios[key].items():
            assert x == c_core["headroom"][key][n] / headroom[key][n]
    assert len(c_core["latency_rounds"]) == 3 and "the same on the C core" in out_text


def test_the_emulator_is_found_through_its_entry_point(monkeypatch: pytest.MonkeyPatch) -> None:
    emulator = live.load_emulator()  # this checkout registers firmware_model's
    assert emulator.nv_file_bytes == 2 * SLOT_SIZE and emulator.nv_record_bytes == RECORD_SIZE
    monkeypatch.setattr(live, "entry_points", lambda group: [])
    with pytest.raises(live.EmulatorMissing, match=r"none registered under the canergy\.emulators"):
        live.load_emulator()


def test_a_turn_runs_from_a_frame_received_to_the_next_sent() -> None:
    us = 1e-6  # (time, sent): in at 0, out at 10; in at 30, in at 50, out at 90
    stamps = [(0.0, False), (10 * us, True), (30 * us, False), (50 * us, False), (90 * us, True)]
    assert live.turn_us(stamps) == pytest.approx(25.0)  # the median of 10 and 40
    assert live.turn_us([(0.0, True), (1.0, True)]) is None  # nothing received: no turn


def test_the_latency_profile_leaves_the_bus_what_the_turns_do_not_take() -> None:
    profile = live.latency_profile(1.0, 100.0, 150.0)  # 1 ms; turns of 100 and 150 us
    assert profile == {
        "supervisor_turn_us": 100.0,
        "nodes_turn_us": 150.0,
        "bus_hop_us": 125.0,  # (1000 - 200 - 300) / 4
        "nodes_and_bus_us": 800.0,
    }
    assert live.latency_profile(1.0, 100.0, None)["bus_hop_us"] is None  # nodes not seen
    assert live.latency_profile(None, 100.0, 150.0) is None


def test_the_paced_alone_loop_reads_one_frame_per_pass(tmp_path: Path) -> None:
    """Own code frame by frame: each supervisor pass reads at most one frame, where the unpaced
    loop reads what 16 nodes sent in their turn."""
    emulator = live.load_emulator()
    (tmp_path / "hot").mkdir()
    (tmp_path / "paced").mkdir()
    hot = alone.supervisor_alone(emulator, 16, 0.3, tmp_path / "hot")
    paced = alone.supervisor_alone(emulator, 16, 0.3, tmp_path / "paced", pace_s=0.0)
    assert paced["frames"] > 0 and paced["supervisor_cpu_us_per_frame"] > 0
    assert paced["frames_received_per_pass"] <= 1.0 < hot["frames_received_per_pass"]


@pytest.mark.parametrize("core", ["python", "c"])
def test_the_live_bench_runs_in_another_identifier_block(tmp_path: Path, core: str) -> None:
    """``canergy bench --id-base``: the supervisor (either core) encodes in the bus's block,
    where the nodes listen; in canergy's default block they would never answer."""
    from canergy.ccore.supervisor import missing

    if core == "c" and missing() is not None and not os.environ.get("CANERGY_REQUIRE_CCORE"):
        pytest.skip(str(missing()))
    row = live.canergy_grants(live.load_emulator(), 2, 0.3, tmp_path, core=core, id_base=0x0CF00000)
    assert row["transactions"] > 0 and row["core"] == core


@pytest.mark.parametrize(("auth", "layout"), [(False, "fd"), (True, "fd"), (True, "classic")])
def test_the_auth_frame_path_bench_measures_the_c_path(auth: bool, layout: str) -> None:
    """``canergy bench``'s plain against ``--auth`` FD figure (and the classic layout's)
    runs the C core's frame path in both (answers taken in C, nothing refused), so its ratio
    compares what it says."""
    from canergy.auth.frames import Layout
    from canergy.bench.auth_path import supervisor_cpu
    from canergy.ccore.supervisor import missing

    if missing() is not None:
        pytest.skip(missing())
    row = supervisor_cpu(4, 0.05, auth=auth, layout=Layout(layout))
    assert row["frame_path"] == "c" and row["refused"] == 0
    assert row["frames_in_c"] > 0 and row["frames"] > 0
