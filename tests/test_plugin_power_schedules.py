"""Power cuts drawn by hypothesis (``fault_schedules(power=power_cuts([...]))``), each example a
run of its own with the plugin's ``Books``: the emulator as a process (on Zenoh over loopback,
behind the bridge from the virtual bus) killed and started again as drawn, each cut counted
(overlapping cuts one), grants after the last, and the books closed."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from canergy.bridge.schedule import FaultSchedule, PowerCut
from canergy.testing.bus import TestBus
from canergy.testing.plugin import Books
from canergy.testing.run import until
from canergy.testing.strategies import fault_profiles, fault_schedules, power_cuts

FLAGS = ["--nodes", "1", "--initial", "20J", "--target", "1J", "--max-grant", "0.3J"]
FAST = ["--response-timeout", "0.2"]


def outages(cuts: tuple[PowerCut, ...]) -> list[tuple[int, int]]:
    """The times the node is off: overlapping or touching cuts are one."""
    merged: list[tuple[int, int]] = []
    for cut in sorted(cuts, key=lambda c: c.start_us):
        end = cut.start_us + cut.length_us
        if merged and cut.start_us <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], end))
        else:
            merged.append((cut.start_us, end))
    return merged


def _run(schedule: FaultSchedule, tmp: Path) -> None:
    books = Books(tmp)
    up, below = TestBus.virtual(), TestBus.zenoh()
    status = tmp / "node1-status.json"
    node = [sys.executable, "-m", "firmware_model", "--node", "1", *below.flags]
    node += ["--nv", str(tmp / "n1.nv"), "--no-fsync", "--status-file", str(status)]
    node += ["--status-period", "0.2", "--power", "0.5W", *FAST]
    try:
        process = books.process("node1", node, status)  # there when its first cut falls due
        bridge = books.bridge(up, below, schedule)
        books.add_client(status)
        sup = books.supervisor(up, [*FLAGS, *FAST])
        off = outages(schedule.power_cuts)
        end_s = max(e for _, e in off) / 1e6
        until(lambda: bridge.status()["uptime_s"] > end_s, "the last cut's end")
        done = sup.status()["nodes"]["1"]["committed"]
        sup.wait_for(lambda s: s["nodes"]["1"]["committed"] > done, "a grant after the cuts")
        power = bridge.status()["power"]["node1"]
        assert (power["cuts"], power["restarts"], power["off"]) == (len(off), len(off), False)
        assert process.starts == 1 + len(off)
    finally:
        books.stop_all()
    assert books.verdict() is None


@settings(
    max_examples=2,
    deadline=None,
    phases=[Phase.generate],  # each example takes seconds: no shrinking, no replay database
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    schedule=fault_schedules(
        fault_profiles(max_probability=0.1, max_delay_us=1_000),
        st.just([]),
        power_cuts(["node1"], max_start_us=2_000_000, max_length_us=1_000_000),
    ).filter(lambda s: len(s.power_cuts) > 0)
)
def test_drawn_power_cuts_are_made_and_the_books_close(
    schedule: FaultSchedule, tmp_path_factory: pytest.TempPathFactory
) -> None:
    _run(schedule, tmp_path_factory.mktemp("run"))
