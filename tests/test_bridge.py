"""The fault-injecting bridge: its schedule (seeded, replayable, counted), the bridge between two
python-can buses, and ``canergy bridge`` between a supervisor and its nodes."""

from __future__ import annotations

import json
import re
import signal
import threading
import time
import uuid
from pathlib import Path

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st
from support.live_rig import Loop

from canergy.bridge.link import Bridge
from canergy.bridge.schedule import FaultSchedule, Partition, PowerCut, parse_faults
from canergy.cli import main
from canergy.codec import Codec
from canergy.faults import FaultProfile
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.live.supervisor.control import request
from canergy.messages import Direction
from canergy.testing.strategies import fault_schedules, power_cuts
from firmware_model.__main__ import status as node_status
from firmware_model.actuator import PowerProfile
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore

FAULTS = FaultProfile(
    loss=0.2, duplicate=0.2, reorder=0.2, corrupt=0.2, delay_us=500, jitter_us=500
)


def _frames(n: int) -> list[bytes]:
    return [bytes([i % 256, i // 256, 7]) for i in range(n)]


def _decisions(schedule: FaultSchedule, direction: int, frames: list[bytes]) -> list[object]:
    return [schedule.fate(direction, data, 1000 * i) for i, data in enumerate(frames)]


def test_the_same_seed_gives_the_same_decisions_and_another_seed_others() -> None:
    frames = _frames(500)
    first = _decisions(FaultSchedule(FAULTS, 7), 0, frames)
    assert first == _decisions(FaultSchedule(FAULTS, 7), 0, frames)
    assert first != _decisions(FaultSchedule(FAULTS, 8), 0, frames)
    assert first != _decisions(FaultSchedule(FAULTS, 7), 1, frames)  # each direction its own


def test_a_directions_decisions_do_not_depend_on_the_other_direction_nor_on_the_data() -> None:
    alone = FaultSchedule(FAULTS, 3)
    busy = FaultSchedule(FAULTS, 3)
    mine, theirs = _frames(300), [b"\xff" * 8] * 300
    got = []
    for i, data in enumerate(mine):
        busy.fate(1, theirs[i], 1000 * i)
        got.append(busy.fate(0, data, 1000 * i))
    assert got == _decisions(alone, 0, mine)
    # other data of the same length: the same copies, delays and flipped bits
    other = [bytes(b ^ 0x55 for b in d) for d in mine]
    again = _decisions(FaultSchedule(FAULTS, 3), 0, other)
    assert [[d for d, _ in fate] for fate in again] == [[d for d, _ in fate] for fate in got]


@pytest.mark.parametrize(
    ("profile", "counted"),
    [
        (FaultProfile(loss=1.0), "lost"),
        (FaultProfile(duplicate=1.0), "duplicated"),
        (FaultProfile(reorder=1.0), "reordered"),
        (FaultProfile(corrupt=1.0), "corrupted"),
    ],
)
def test_each_fault_does_what_it_counts(profile: FaultProfile, counted: str) -> None:
    schedule = FaultSchedule(profile, 1)
    frames = _frames(100)
    fates = _decisions(schedule, 0, frames)
    counts = schedule.as_json()["directions"][0]  # type: ignore[index]
    assert counts["frames"] == 100 and counts[counted] == 100
    copies = [c for fate in fates for c in fate]  # type: ignore[attr-defined]
    if counted == "lost":
        assert copies == [] and counts["lost"] == 100
    if counted == "duplicated":
        assert len(copies) == 200
    if counted == "reordered":  # held back by up to 20 ms more than the 350 +- 150 us
        late = [due - 1000 * i for i, fate in enumerate(fates) for due, _ in fate]  # type: ignore[attr-defined]
        assert min(late) > 200 and max(late) <= 20_500 and sum(late) / len(late) > 5000
    if counted == "corrupted":  # exactly one bit flipped in each
        for (_, out), data in zip(copies, frames, strict=True):
            diff = int.from_bytes(out, "big") ^ int.from_bytes(data, "big")
            assert diff.bit_count() == 1
    others = {"lost", "duplicated", "reordered", "corrupted"} - {counted}
    assert all(counts[k] == 0 for k in others)


def test_loss_and_duplication_counts_match_their_probabilities() -> None:
    schedule = FaultSchedule(FaultProfile(loss=0.1, duplicate=0.2), 11)
    copies = sum(len(f) for f in _decisions(schedule, 1, _frames(5000)))  # type: ignore[arg-type]
    c = schedule.counts[1].faults
    assert 400 < c.lost < 600 and 800 < c.duplicated < 1000
    assert copies == 5000 - c.lost + c.duplicated


def test_a_partition_drops_both_ways_for_its_window_and_draws_nothing() -> None:
    cut = Partition.parse("2ms+3ms")
    assert (cut.start_us, cut.length_us, str(cut)) == (2000, 3000, "2ms+3ms")
    schedule = FaultSchedule(FAULTS, 5, [cut])
    plain = FaultSchedule(FAULTS, 5)
    for t in range(0, 10_000, 500):
        for direction in (0, 1):
            fate = schedule.fate(direction, b"\x01\x02", t)
            if 2000 <= t < 5000:
                assert fate == []
            else:  # the uncut run's fates, but for copies that would arrive during the cut
                expected = plain.fate(direction, b"\x01\x02", t)
                assert fate == [c for c in expected if not cut.covers(c[0])]
    assert [c.partitioned for c in schedule.counts] == [6, 6]
    assert schedule.as_json()["directions"][0]["frames"] == 20  # type: ignore[index]


def test_a_copy_delayed_into_a_partition_never_arrives() -> None:
    """Held back past the cut's start (reordered, 20 ms at most), a copy is in flight when the
    link is cut: it is dropped and counted, and nothing arrives during the cut."""
    schedule = FaultSchedule(FaultProfile(reorder=1.0), 2, [Partition(20_000, 100_000)])
    fates = [schedule.fate(0, b"\x01", t) for t in range(0, 20_000, 100)]
    dues = [due for fate in fates for due, _ in fate]
    c = schedule.counts[0]
    assert c.cut_in_flight > 50 and len(dues) == 200 - c.cut_in_flight
    assert not any(20_000 <= due < 120_000 for due in dues)
    assert schedule.as_json()["directions"][0]["cut_in_flight"] == c.cut_in_flight  # type: ignore[index]


@pytest.mark.parametrize("text", ["2s", "2s+0s", "x+1s", "-1s+2s", "+"])
def test_a_bad_partition_is_refused(text: str) -> None:
    with pytest.raises(ValueError):
        Partition.parse(text)


def test_faults_as_text() -> None:
    profile, cuts, power = parse_faults(
        "loss=0.1, duplicate=0.05,delay=2ms,jitter=1ms,partition=2s+1s,cut=n1@3s+1s,cut=4s+50ms"
    )
    assert (profile.loss, profile.duplicate, profile.delay_us, profile.jitter_us) == (
        0.1,
        0.05,
        2000,
        1000,
    )
    assert cuts == (Partition(2_000_000, 1_000_000),)
    assert power == (PowerCut(3_000_000, 1_000_000, "n1"), PowerCut(4_000_000, 50_000))
    assert [str(c) for c in power] == ["n1@3s+1s", "4s+50ms"]
    assert parse_faults("") == (FaultProfile(delay_us=0, jitter_us=0), (), ())


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("loss=2", "loss probability 2.0 outside 0..1"),
        ("loss=nan", "outside 0..1"),
        ("loss", "give KEY=VALUE"),
        ("drop=0.1", "unknown fault (known: loss, duplicate"),
        ("delay=1ms,jitter=2ms", "jitter larger than the delay"),
        ("partition=3s", "AT+FOR"),
        ("cut=n1@3s", "AT+FOR"),
        ("cut=@3s+1s", "give NAME@AT+FOR or AT+FOR"),
        ("cut=n 1@3s+1s", "node name 'n 1': letters, digits"),
        ("cut=n1@3s+0s", "lasts more than 0"),
    ],
)
def test_bad_faults_as_text_are_named(text: str, message: str) -> None:
    with pytest.raises(ValueError, match=re.escape(message)):
        parse_faults(text)


def test_power_cuts_fall_due_once_each_in_time_order() -> None:
    schedule = FaultSchedule(
        FAULTS, 1, power_cuts=[PowerCut(2_000, 3_000, "b"), PowerCut(1_000, 1_000, "a")]
    )
    assert schedule.next_power_event() == 1_000
    assert schedule.power_events(999) == []
    assert schedule.power_events(2_000) == [(False, "a"), (False, "b"), (True, "a")]
    assert schedule.power_events(2_000) == []  # given once
    assert schedule.next_power_event() == 5_000
    assert schedule.power_events(10_000) == [(True, "b")]
    assert schedule.next_power_event() is None


class _Node:
    """A node process as the bridge switches it: what was done to it, in order."""

    def __init__(self, name: str, done: list[str], fail: bool = False) -> None:
        self.name, self.done, self.fail = name, done, fail

    def power_cut(self) -> None:
        if self.fail:
            raise OSError("no such process")
        self.done.append(f"{self.name} off")

    def restart(self) -> None:
        self.done.append(f"{self.name} on")


def test_the_bridge_cuts_node_processes_power_as_scheduled_and_counts_it() -> None:
    """Overlapping cuts keep a process off until the last ends (one kill, one restart); a cut
    without a name switches every process; a name it was not given is reported, not fatal."""
    clock, done = _Clock(), []
    nodes = {n: _Node(n, done) for n in ("a", "b")}
    cuts = [PowerCut(0, 300_000, "a"), PowerCut(100_000, 300_000, "a")]
    cuts += [PowerCut(500_000, 100_000), PowerCut(700_000, 10_000, "zz")]
    schedule = FaultSchedule(FaultProfile(delay_us=0, jitter_us=0), 0, power_cuts=cuts)
    channel = uuid.uuid4().hex
    buses = (_virtual(f"a-{channel}"), _virtual(f"b-{channel}"))
    bridge = Bridge(buses, schedule, clock=clock, processes=nodes)
    try:
        for t in (0, 150_000, 350_000, 400_000, 550_000, 600_000, 800_000):
            clock.now = bridge.start_us + t
            bridge.poll(0)
            if t == 350_000:
                assert done == ["a off"]  # still off: the second cut lasts to 400 ms
                assert bridge.status()["power"]["a"] == {"cuts": 1, "restarts": 0, "off": True}
        assert done == ["a off", "a on", "a off", "b off", "a on", "b on"]
        status = bridge.status()
        assert status["power"] == {
            "a": {"cuts": 2, "restarts": 2, "off": False},
            "b": {"cuts": 1, "restarts": 1, "off": False},
        }
        assert status["power_errors"] == [
            "power cut of 'zz': no such node process (a, b); start it before its cut falls due"
        ]
        shown = ["a@0s+300ms", "a@100ms+300ms", "500ms+100ms", "zz@700ms+10ms"]
        assert status["power_cuts"] == shown
    finally:
        bridge.close()
        for bus in buses:
            bus.shutdown()


def test_restoring_power_ends_the_cuts_on_and_makes_no_more() -> None:
    clock, done = _Clock(), []
    nodes = {"a": _Node("a", done), "b": _Node("b", done, fail=True)}
    cuts = [PowerCut(0, 10_000_000, "a"), PowerCut(0, 10_000_000, "b"), PowerCut(20_000_000, 1)]
    schedule = FaultSchedule(FaultProfile(delay_us=0, jitter_us=0), 0, power_cuts=cuts)
    channel = uuid.uuid4().hex
    buses = (_virtual(f"a-{channel}"), _virtual(f"b-{channel}"))
    bridge = Bridge(buses, schedule, clock=clock, processes=nodes)
    try:
        bridge.poll(0)
        bridge.restore_power()
        clock.now += 30_000_000
        bridge.poll(0)
        assert done == ["a off", "a on"]
        assert bridge.status()["power_errors"] == ["power off of 'b': OSError('no such process')"]
    finally:
        bridge.close()
        for bus in buses:
            bus.shutdown()


def test_a_bridge_told_to_cut_power_needs_the_processes() -> None:
    schedule = FaultSchedule(FAULTS, 0, power_cuts=[PowerCut(0, 1)])
    with pytest.raises(ValueError, match="give the bridge them"):
        Bridge((_virtual("x"), _virtual("y")), schedule)
    channel = uuid.uuid4().hex
    buses = (_virtual(f"a-{channel}"), _virtual(f"b-{channel}"))
    bridge = Bridge(buses, schedule, clock=_Clock(), processes={})  # none yet, none ever
    try:
        bridge.poll(0)
        assert bridge.status()["power_errors"] == ["power cut of every node process: there is none"]
    finally:
        bridge.close()
        for bus in buses:
            bus.shutdown()


class _Clock:
    def __init__(self) -> None:
        self.now = 1_000_000

    def __call__(self) -> int:
        return self.now


def _virtual(channel: str) -> can.BusABC:
    return can.Bus(interface="virtual", channel=channel)


def test_the_bridge_carries_frames_late_as_scheduled_and_captures_both_buses(
    tmp_path: Path,
) -> None:
    a, b = f"a-{uuid.uuid4().hex}", f"b-{uuid.uuid4().hex}"
    clock = _Clock()
    ends = [_virtual(a), _virtual(b)]
    inner = [_virtual(a), _virtual(b)]
    schedule = FaultSchedule(FaultProfile(duplicate=1.0, delay_us=10_000, jitter_us=0), 0)
    log = tmp_path / "capture.asc"
    capture = can.Logger(str(log))
    bridge = Bridge((inner[0], inner[1]), schedule, names=(a, b), capture=capture, clock=clock)
    try:
        fd = can.Message(arbitration_id=0x1234, is_extended_id=True, is_fd=True, data=bytes(12))
        ends[0].send(fd)
        ends[1].send(can.Message(arbitration_id=0x12, is_extended_id=False, data=b"\x05"))
        deadline = time.monotonic() + 10
        while sum(c.faults.frames for c in schedule.counts) < 2:
            bridge.poll(0.01)  # decides both frames; none is due yet
            assert time.monotonic() < deadline
        assert ends[1].recv(0.05) is None and ends[0].recv(0.05) is None
        clock.now += 10_000
        bridge.poll(0)
        got_b = [ends[1].recv(1), ends[1].recv(1)]
        got_a = [ends[0].recv(1), ends[0].recv(1)]
    finally:
        bridge.close()
        capture.stop()
        for bus in (*ends, *inner):
            bus.shutdown()
    assert all(m is not None and m.is_fd and len(m.data) == 12 for m in got_b)
    assert all(m is not None and m.arbitration_id == 0x12 for m in got_a)
    status = bridge.status()
    assert status["directions"][f"{a}>{b}"]["forwarded"] == 2
    assert status["directions"][f"{b}>{a}"]["duplicated"] == 1
    logged = list(can.LogReader(str(log)))
    assert len(logged) == 6  # two received, four sent
    assert sum(1 for m in logged if m.arbitration_id == 0x1234) == 3


def test_canergy_bridge_refuses_bad_values(capsys: pytest.CaptureFixture[str]) -> None:
    two = ["--bus1-interface", "virtual", "--bus1-channel", "x", "--bus2-interface", "virtual"]
    assert main(["bridge", *two, "--bus2-channel", "x"]) == 2
    assert "name the same bus 'x'" in capsys.readouterr().err
    assert main(["bridge", *two, "--bus2-channel", "y", "--delay", "1ms", "--jitter", "2ms"]) == 2
    assert "--jitter 2ms is above --delay 1ms" in capsys.readouterr().err
    assert main(["bridge", *two, "--bus2-channel", "y", "--log", "c.nope"]) == 2
    assert "unknown log format" in capsys.readouterr().err
    for flags, message in (
        (["--loss", "1.5"], "outside 0..1"),
        (["--partition", "3s"], "AT+FOR"),
        (["--seed", "-1"], "seed"),
    ):
        with pytest.raises(SystemExit):
            main(["bridge", *two, "--bus2-channel", "y", *flags])
        assert message in capsys.readouterr().err


def _nodes(tmp: Path, channel: str, ids: list[int]) -> tuple[NodeHost, Loop]:
    now = monotonic_us()
    config = NodeConfig(power=PowerProfile.constant(0.5), telemetry_period_us=200_000)
    host = NodeHost(
        [FirmwareNode(n, NvStore(tmp / f"{n}.nv", n, fsync=False), config, now) for n in ids]
    )
    bus = can.Bus(interface="virtual", channel=channel)
    return host, Loop(BusRuntime(bus, host, codec=Codec(), receives=Direction.TO_CLIENT))


def test_a_supervisor_and_its_nodes_across_a_lossy_duplicating_bridge_close_the_books(
    tmp_path: Path,
) -> None:
    """``canergy supervisor`` on one virtual bus, emulated nodes on another, the bridge with
    10% loss and 10% duplication each way between: grants commit and ``canergy ledger`` closes
    the books over the two status files."""
    up, down = f"sup-{uuid.uuid4().hex}", f"nodes-{uuid.uuid4().hex}"
    control, status = tmp_path / "ctl.sock", tmp_path / "sup.json"
    faults = FaultProfile(loss=0.1, duplicate=0.1, delay_us=0, jitter_us=0)
    schedule = FaultSchedule(faults, 42)
    buses = (_virtual(up), _virtual(down))
    bridge = Bridge(buses, schedule, names=(up, down))
    stop = threading.Event()
    carrier = threading.Thread(target=bridge.run, args=(stop.is_set,), daemon=True)
    carrier.start()
    host, loop = _nodes(tmp_path, down, [1, 2, 3])
    argv = [
        *("supervisor", "-i", "virtual", "-c", up, "--nodes", "1-3", "--initial", "20J"),
        *("--target", "1J", "--max-grant", "0.5J", "--state", str(tmp_path / "state.json")),
        *("--status-file", str(status), "--control", str(control), "--no-fsync"),
        *("--response-timeout", "50ms"),
    ]
    result: list[int] = []
    supervisor = threading.Thread(target=lambda: result.append(main(argv)), daemon=True)
    supervisor.start()
    try:
        deadline = time.monotonic() + 60
        while not control.exists() or not _all_topped_up(control):
            assert time.monotonic() < deadline, "the nodes were never topped up"
            time.sleep(0.1)
        answer = request(control, {"grant": {"node": 2, "amount_uj": 300_000}}, 30)
        assert answer.get("outcome") in ("COMMITTED", "ABORTED"), answer
        # grants until each direction has lost and duplicated a frame: which frames the
        # seeded schedule hits depends on how many crossed (a loaded run had 20 frames from
        # the supervisor, none of them duplicated)
        while not _both_faults(bridge):
            assert time.monotonic() < deadline + 60, bridge.status()["directions"]
            answer = request(control, {"grant": {"node": 2, "amount_uj": 1_000}}, 30)
            assert answer.get("outcome") in ("COMMITTED", "ABORTED"), answer
        assert request(control, {"stop": True}, 30) == {"stopping": True}
        supervisor.join(timeout=60)
        assert result == [0]
    finally:
        loop.halt()
        stop.set()
        carrier.join(timeout=10)
        bridge.close()
        for bus in buses:
            bus.shutdown()
    nodes = tmp_path / "nodes.json"
    nodes.write_text(json.dumps(node_status(host, loop.runtime)))
    counts = bridge.status()["directions"]
    assert all(c["lost"] > 0 and c["duplicated"] > 0 for c in counts.values()), counts
    assert main(["ledger", "--level", str(status), str(nodes)]) == 0
    assert sum(n.client.state.credited for n in host.nodes.values()) >= 3 * 500_000


def _both_faults(bridge: Bridge) -> bool:
    counts = bridge.status()["directions"].values()
    return all(c["lost"] > 0 and c["duplicated"] > 0 for c in counts)


def _all_topped_up(control: Path) -> bool:
    try:
        books = request(control, {"status": True}, 5)
    except OSError:
        return False
    return all(n["delivered_uj"] >= 1_000_000 for n in books["nodes"].values())


def test_canergy_bridge_reports_captures_and_stops_on_sigterm(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The command in this process's main thread: frames sent on one virtual bus arrive on the
    other (duplicated), the status file counts them, the capture holds both buses, SIGTERM
    stops it with a last status line."""
    a, b = f"a-{uuid.uuid4().hex}", f"b-{uuid.uuid4().hex}"
    status, log = tmp_path / "bridge.json", tmp_path / "bridge.log"
    ends = (_virtual(a), _virtual(b))
    got: list[can.Message] = []

    def drive() -> None:  # once the bridge's buses are open, send; once counted, stop it
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            ends[0].send(can.Message(arbitration_id=0x0CE00105, data=b"\x01\x02"))
            frame = ends[1].recv(0.1)
            if frame is not None:
                got.append(frame)
                break
        while time.monotonic() < deadline and len(got) < 2:
            frame = ends[1].recv(0.1)
            if frame is not None:
                got.append(frame)
        while time.monotonic() < deadline:
            if status.exists() and json.loads(status.read_text())["held"] == 0:
                break
            time.sleep(0.05)
        signal.raise_signal(signal.SIGTERM)

    argv = [
        *("bridge", "--bus1-interface", "virtual", "--bus1-channel", a),
        *("--bus2-interface", "virtual", "--bus2-channel", b, "--duplicate", "1"),
        *("--seed", "9", "--status-file", str(status), "--status-period", "50ms"),
        *("--log", str(log)),
    ]
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    driver = threading.Thread(target=drive, daemon=True)
    driver.start()
    try:
        assert main(argv) == 0
    finally:
        for s, handler in handlers.items():
            signal.signal(s, handler)
        driver.join(timeout=30)
        for bus in ends:
            bus.shutdown()
    assert len(got) >= 2 and got[0].data == got[1].data == b"\x01\x02"
    final = json.loads(status.read_text())
    forward = final["directions"][f"{a}>{b}"]
    assert final["seed"] == 9 and forward["duplicated"] == forward["frames"] >= 1
    assert forward["forwarded"] == 2 * forward["frames"]
    err = capsys.readouterr().err
    assert f"canergy bridge: {a} <-> {b}, seed 9" in err
    assert f"{a}>{b} {forward['frames']} frames, {forward['forwarded']} forwarded" in err
    channels = [line.split()[1] for line in log.read_text().splitlines()]
    assert channels.count(a) == forward["frames"] and channels.count(b) == forward["forwarded"]


@given(fault_schedules(), st.lists(st.binary(max_size=8), max_size=60))
def test_any_drawn_schedule_replays_from_its_seed(
    schedule: FaultSchedule, frames: list[bytes]
) -> None:
    """What the hypothesis strategy draws is a valid schedule, and a second schedule with its
    profile, seed and partitions makes the same decisions on the same frames."""
    again = FaultSchedule(schedule.profile, schedule.seed, schedule.partitions, schedule.power_cuts)
    for i, data in enumerate(frames):
        t = 250_000 * i
        assert schedule.fate(i % 2, data, t) == again.fate(i % 2, data, t)
    assert schedule.as_json() == again.as_json()


@given(fault_schedules(power=power_cuts(["node1", "node2"])))
def test_a_schedule_shows_what_makes_the_same_decisions(schedule: FaultSchedule) -> None:
    """A failing example's schedule, as hypothesis prints it, rebuilds the schedule that failed,
    its power cuts too."""
    scope = {"FaultSchedule": FaultSchedule, "FaultProfile": FaultProfile, "Partition": Partition}
    again = eval(repr(schedule), {**scope, "PowerCut": PowerCut})
    assert again.power_cuts == schedule.power_cuts
    events = [schedule.power_events(t) for t in range(0, 12_000_000, 500_000)]
    assert [again.power_events(t) for t in range(0, 12_000_000, 500_000)] == events
    frames = [bytes([i]) * 8 for i in range(40)]
    for direction in (0, 1):
        fates = [schedule.fate(direction, f, i * 50_000) for i, f in enumerate(frames)]
        assert [again.fate(direction, f, i * 50_000) for i, f in enumerate(frames)] == fates
