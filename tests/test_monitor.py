"""`canergy monitor` without a terminal: the model, the keys, the rendered text, the feeds."""

from __future__ import annotations

import json
import os
import re
import socket
import threading
import time
import uuid
from pathlib import Path

import can
import pytest
from support import monitor_scenario as scenario
from support.live_rig import Rig
from support.monitor_scenario import cell

from canergy.cli import main
from canergy.codec import Codec
from canergy.core import Supervisor
from canergy.demo import DemoConfig, run_demo
from canergy.faults import FaultProfile
from canergy.frame_bits import frame_bits
from canergy.inspect.captures import read_file
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.control import ControlServer
from canergy.live.supervisor.service import ServiceConfig
from canergy.messages import Intention, Telemetry
from canergy.monitor.books import from_control, from_status_file, parse_status
from canergy.monitor.busload import fd_frame_bits, frame_seconds
from canergy.monitor.feeds import LiveFeed, ModelListener, ReplayFeed, enlarge_receive_buffer
from canergy.monitor.model import MonitorModel, Row
from canergy.monitor.render import Context, bar, screen, sparkline
from canergy.monitor.sessions import Ending, Phase
from canergy.monitor.tui import Display
from canergy.monitor.view import View, parse_filter

J = 1_000_000


def fed(frames: list[can.Message], **kwargs: object) -> MonitorModel:
    model = MonitorModel(Codec(), **kwargs)  # type: ignore[arg-type]
    for f in frames:
        model.feed(f, f.timestamp)
    return model


def row(model: MonitorModel, node: int, now: float | None = None) -> Row:
    snap = model.snapshot(now if now is not None else scenario.T0 + scenario.GAP + 1)
    return next(r for r in snap.rows if r.node == node)


# -- the model ------------------------------------------------------------------------------
def test_a_write_off_shows_when_the_next_intention_carries_it() -> None:
    frames = scenario.frames()
    before = fed(frames[: scenario.WRITE_OFF_AT])
    five = row(before, 5, scenario.T0 + 0.3)
    assert (five.phase, five.sends, five.write_offs, five.tx) == (Phase.INTENTION, 3, 0, 1)
    assert five.lost  # it never said a word
    after = fed(frames[: scenario.WRITE_OFF_AT + 1])
    five = row(after, 5)
    assert (five.write_offs, five.commits, five.aborts, five.tx) == (1, 0, 0, 2)
    assert five.last_outcome is not None and five.last_outcome.ending is Ending.WRITTEN_OFF
    assert five.last_outcome.amount_uj == 300_000 and five.granted_uj == 300_000
    done = row(fed(frames), 5)
    assert (done.commits, done.write_offs, done.phase, done.granted_uj) == (1, 1, None, 500_000)


def test_an_unanswered_transaction_whose_gs_did_not_grow_was_aborted() -> None:
    codec = Codec()
    model = MonitorModel(codec)
    for t, m in enumerate([Intention(7, 1, 400, 0), Intention(7, 2, 100, 0)]):
        ident, data = codec.encode(m)
        model.feed(can.Message(arbitration_id=ident, data=data, timestamp=t), float(t))
    seven = row(model, 7, 2.0)
    assert (seven.aborts, seven.write_offs, seven.granted_uj) == (1, 0, 0)


def test_levels_returns_errors_and_the_audit_bound() -> None:
    model = fed(scenario.frames())
    three = row(model, 3)
    assert (three.level_uj, three.level_source) == (630_000, "telemetry")
    assert (three.returns, three.returned_uj, three.commits, three.damaged) == (1, 120_000, 1, 1)
    five = row(model, 5)
    assert five.level_source == "bound" and five.level_uj == 500_000  # 0.3 written off + 0.2
    snap = model.snapshot(scenario.T0 + scenario.GAP + 1)
    assert (snap.frames, snap.foreign, snap.errors) == (17, 1, {"crc": 1})
    assert snap.alarms == ()  # an honest capture


def test_passive_counts_equal_the_demo_s_own(tmp_path: Path) -> None:
    """The demo's supervisor counts its outcomes; the monitor sees only its frames."""
    log = tmp_path / "demo.log"
    result = run_demo(
        DemoConfig(
            nodes=(1, 2, 3, 4, 5),
            transactions=200,
            duration_us=300 * J,
            initial=10 * J,
            variant="hardened",
            faults=FaultProfile(loss=0.1, duplicate=0.05, reorder=0.05, corrupt=0.01),
            seed=3,
            resets=2,
            commit_ratio=0.8,
            log=log,
        )
    )
    model = fed(list(read_file(log, lambda *a: None)))
    rows = model.snapshot(1e12).rows
    assert sum(r.commits for r in rows) == result.outcomes["committed"]
    assert sum(r.aborts for r in rows) == result.outcomes["aborted"]
    assert sum(r.write_offs for r in rows) == result.outcomes["written_off"] >= 1


def test_rate_and_bus_load_over_the_last_second() -> None:
    codec = Codec()
    ident, data = codec.encode(Telemetry(1, 100))
    model = MonitorModel(codec, bitrate=250_000)
    for i in range(500):  # 500 frames in one second, then one more second of nothing
        model.feed(can.Message(arbitration_id=ident, data=data, timestamp=0), i / 500)
    snap = model.snapshot(0.999)
    assert snap.frames_per_s == 500
    assert snap.load == pytest.approx(500 * frame_bits(len(data), True, False) / 250_000)
    later = model.snapshot(2.0)
    assert later.frames_per_s == 0 and later.load == 0 and later.frames == 500


def test_frame_times_classic_and_fd() -> None:
    classic = can.Message(arbitration_id=0x123, data=bytes(8), is_extended_id=False)
    assert frame_seconds(classic, 500_000) == 111 / 500_000
    assert fd_frame_bits(64, extended=True) == (36 + 13, 1 + 4 + 512 + 4 + 21 + 7)
    fd = can.Message(arbitration_id=1, data=bytes(64), is_fd=True, bitrate_switch=True)
    assert frame_seconds(fd, 500_000, 2_000_000) == pytest.approx(49 / 500e3 + 549 / 2e6)


# -- the books ------------------------------------------------------------------------------
def _status() -> dict[str, object]:
    service = build_service(Supervisor([3, 5], 10 * J), ServiceConfig(), 0)
    return service.status()


def test_the_books_of_a_real_supervisor_status_join_the_rows(tmp_path: Path) -> None:
    path = tmp_path / "status.json"
    status = _status()
    status["nodes"]["5"]["written_off"] = 1  # type: ignore[index]
    path.write_text(json.dumps(status))
    model = fed(scenario.frames())
    model.set_books(from_status_file(path, scenario.T0 + scenario.GAP))
    status["usable_uj"] = 9 * J
    path.write_text(json.dumps(status))
    written = time.time() - 5  # the supervisor last rewrote it five seconds ago
    os.utime(path, (written, written))
    model.set_books(from_status_file(path, scenario.T0 + scenario.GAP + 0.5))
    snap = model.snapshot(scenario.T0 + scenario.GAP + 1)
    assert [uj for _, uj in snap.usable_history] == [10 * J, 9 * J] and snap.books is not None
    five = next(r for r in snap.rows if r.node == 5)
    assert five.books is not None and (five.books.state, five.books.written_off) == ("IDLE", 1)
    text = "\n".join(t for t, _ in screen(snap, View(), Context("x", "live"), 200, 20))
    assert "supervisor usable 9.000 J █▁ (9.000 J .. 10.000 J in 1.0s)" in text
    assert "| IDLE" in text
    assert re.search(r"books (5\.[5-9]|[6-9]\.\d)s old", text)  # 0.5 s since read, and more


def test_books_keep_the_last_good_status_and_say_why_it_is_old(tmp_path: Path) -> None:
    model = MonitorModel(Codec())
    model.set_books(from_status_file(tmp_path / "missing.json", 0.0))
    assert (
        model.books is not None
        and model.books.error is not None
        and "no such file" in (model.books.error)
    )
    model.set_books(parse_status(_status(), 1.0, "s"))
    (tmp_path / "bad.json").write_text("{")
    model.set_books(from_status_file(tmp_path / "bad.json", 2.0))
    assert model.books.usable_uj == 10 * J and model.books.error is not None
    with pytest.raises(ValueError, match="not a supervisor"):
        parse_status({"role": "client", "usable_uj": 1, "nodes": {}}, 0.0, "s")


def test_books_through_the_control_socket(tmp_path: Path) -> None:
    server = ControlServer(tmp_path / "sup.sock")
    status = _status()
    stop = threading.Event()

    def answer() -> None:
        while not stop.is_set():
            for _, reply in server.pending():
                reply(status)
            time.sleep(0.01)

    worker = threading.Thread(target=answer, daemon=True)
    worker.start()
    try:
        books = from_control(tmp_path / "sup.sock", 1.0, timeout_s=10)
    finally:
        stop.set()
        worker.join()
        server.close()
    assert books.error is None and books.usable_uj == 10 * J
    assert books.nodes is not None and set(books.nodes) == {"3", "5"}
    gone = from_control(tmp_path / "sup.sock", 2.0, timeout_s=1)
    assert gone.error is not None and gone.nodes is None


# -- the view and the text ------------------------------------------------------------------
def test_keys_filter_sort_select_and_raw_view() -> None:
    model = fed(scenario.frames())
    snap = model.snapshot(scenario.T0 + scenario.GAP + 1)
    view = View()
    keys = [r.key for r in view.arrange(snap.rows)]
    assert [k[1] for k in keys] == [3, 5] and view.selected == keys[0]
    view.handle("KEY_DOWN", keys)
    assert view.selected == keys[1]
    for key in "/5-9":
        view.handle(key, keys)
    assert view.prompt == "5-9" and view.nodes is None
    view.handle("\n", keys)
    assert view.nodes == frozenset(range(5, 10)) and view.filter_text == "5-9"
    assert [r.node for r in view.arrange(snap.rows)] == [5]
    view.handle("/", keys)
    for key in ["KEY_BACKSPACE"] * 3 + list("x"):
        view.handle(key, keys)
    view.handle("\n", keys)
    assert view.prompt == "x" and "bad node list" in view.message  # stays open to be fixed
    view.handle("\x1b", keys)
    assert view.prompt is None and view.nodes == frozenset(range(5, 10))
    view.handle("s", keys)
    assert view.sort == "level"
    view.handle("\n", keys)
    assert view.raw
    view.handle("\x1b", keys)
    assert not view.raw
    view.handle("n", keys)
    assert view.steps == 0  # only while paused
    view.handle("p", keys)
    view.handle("n", keys)
    assert view.paused and view.steps == 1
    view.handle("q", keys)
    assert view.quit
    assert parse_filter("") is None and parse_filter("3, 5-7") == {3, 5, 6, 7}


def test_an_empty_filter_shows_every_node_again() -> None:
    """Issue 31: ``/`` then Enter went back to the filter in force, not to every node."""
    snap = fed(scenario.frames()).snapshot(scenario.T0 + scenario.GAP + 1)
    view = View()
    keys = [r.key for r in view.arrange(snap.rows)]
    for typed in ["", "all", "*", " ALL "]:
        for key in "/3\n":
            view.handle(key, keys)
        assert view.nodes == {3} and [r.node for r in view.arrange(snap.rows)] == [3]
        view.handle("/", keys)
        prompt = screen(snap, view, Context("x", "live"), 160, 20)[-1][0]
        assert prompt.startswith("filter nodes (now 3; ") and prompt.endswith(": _")
        for key in [*typed, "\n"]:
            view.handle(key, keys)
        assert view.prompt is None and view.nodes is None and view.filter_text == ""
        assert [r.node for r in view.arrange(snap.rows)] == [3, 5]
        text = [t for t, _ in screen(snap, view, Context("x", "live"), 160, 20)]
        assert any(t.startswith("sort node  filter all  2 nodes") for t in text)
    assert parse_filter("all") is None and parse_filter("*") is None


def test_sorting_puts_trouble_first() -> None:
    snap = fed(scenario.frames()).snapshot(scenario.T0 + scenario.GAP + 1)
    view = View(sort="trouble")
    assert [r.node for r in view.arrange(snap.rows)] == [5, 3]  # a write-off beats a CRC error
    view.sort = "level"
    assert [r.node for r in view.arrange(snap.rows)] == [3, 5]


def test_the_screen_text() -> None:
    model = fed(scenario.frames(), bitrate=500_000)
    snap = model.snapshot(scenario.T0 + scenario.GAP + 1)
    lines = screen(snap, View(), Context("replay s.log", "replay done"), 160, 30)
    assert len(lines) == 30 and all(len(t) <= 160 for t, _ in lines)
    text = [t for t, _ in lines]
    assert text[0].startswith("canergy monitor  replay s.log")
    assert text[0].endswith("replay done: 17 frames") and text[1].startswith("frames 17  ")
    assert "foreign 1 (canopen 1)  decode errors 1: crc 1" in text[1] and "of 500 kbit/s" in text[1]
    three = next(t for t in text if t.lstrip().startswith("3 "))
    assert "0.630 J" in three and "commit 0.500 J" in three and "CRC 1" in three
    five = next(t for t in text if t.lstrip().startswith("5 "))
    head = next(t for t, style in lines if style == "head")
    assert "≤0.500 J" in five
    assert [cell(head, five, title) for title in ("commit", "abort", "w/o", "tx")] == list("1012")
    assert text[-1].startswith("q quit")
    narrow = screen(snap, View(), Context("x", "live", unicode=False), 80, 12)
    assert len(narrow) == 12 and all(len(t) <= 80 for t, _ in narrow)
    assert "<=0.500 J" in "\n".join(t for t, _ in narrow)


def test_the_raw_view_shows_the_node_s_frames() -> None:
    model = fed(scenario.frames())
    snap = model.snapshot(scenario.T0 + scenario.GAP + 1)
    view = View()
    keys = [r.key for r in view.arrange(snap.rows)]
    view.handle("r", keys)
    assert view.raw and view.selected == ("vcan0", 3)
    view.handle("KEY_DOWN", keys)  # the next node's frames
    assert view.raw and view.selected == ("vcan0", 5)
    text = [
        t for t, _ in screen(snap, view, Context("x", "live"), 160, 40, model.raw(view.selected))
    ]
    assert any(t.startswith("raw frames of node 5 on vcan0: the latest 7 of 7") for t in text)
    assert sum("INTENTION      S->5" in t for t in text) == 4
    assert text[-1].startswith("Esc/Enter back")


def test_bars_and_sparklines() -> None:
    assert bar(0.5, 8, True) == "████░░░░" and bar(0.5, 8, False) == "####...."
    assert bar(2.0, 4, True) == "████" and bar(-1, 4, False) == "...."
    assert bar(0.25, 2, True) == "▌░" and bar(1 / 16, 2, True) == "▏░"
    assert sparkline([1, 2, 3, 4], 10, True) == "▁▃▆█"
    assert sparkline([5, 5], 10, False) == "=="
    assert sparkline(range(100), 3, True) == "▁▅█"


# -- the feeds ------------------------------------------------------------------------------
def test_a_replay_keeps_the_capture_s_pace_pauses_and_steps() -> None:
    frames = scenario.frames()
    model, lock = MonitorModel(Codec()), threading.Lock()
    feed = ReplayFeed(iter(frames), model, lock, speed=1.0)
    feed.start()
    try:
        deadline = time.monotonic() + 60
        while feed.fed < scenario.WRITE_OFF_AT and time.monotonic() < deadline:
            time.sleep(0.01)
        assert feed.fed == scenario.WRITE_OFF_AT  # then ten minutes of silence
        feed.pause(True)
        clock = feed.now()
        assert clock < scenario.T0 + 60 and feed.now() == clock  # stopped
        assert "PAUSED" in feed.state(True)
        feed.step()
        assert feed.fed == scenario.WRITE_OFF_AT + 1 and feed.now() == scenario.T0 + scenario.GAP
        with lock:
            assert row(model, 5).write_offs == 1
        feed.pause(False)
        while not feed.done and time.monotonic() < deadline:
            time.sleep(0.01)
        assert feed.fed == len(frames) and feed.state(False) == "replay done"
        assert feed.now() == frames[-1].timestamp  # the clock stops at the last frame
    finally:
        feed.stop()


def test_the_live_feed_counts_every_frame_and_sends_none() -> None:
    channel = f"monitor-{uuid.uuid4().hex}"
    with (
        can.Bus(interface="virtual", channel=channel) as monitor_bus,
        can.Bus(interface="virtual", channel=channel) as sender,
        can.Bus(interface="virtual", channel=channel) as witness,
    ):
        model, lock = MonitorModel(Codec()), threading.Lock()
        feed = LiveFeed(monitor_bus, model, lock)
        feed.start()
        try:
            for f in scenario.frames() * 20:
                sender.send(f)
            deadline = time.monotonic() + 60
            while feed.listener.received < 340 and time.monotonic() < deadline:
                time.sleep(0.01)
        finally:
            feed.stop()
        assert model.frames == feed.listener.received == 340
        seen = 0
        while witness.recv(timeout=0.2) is not None:
            seen += 1
        assert seen == 340  # the sender's frames, not one more
    with lock:
        snap = model.snapshot(time.monotonic())
    assert {r.node: (r.commits, r.write_offs) for r in snap.rows} == {3: (1, 0), 5: (1, 1)}


def test_on_a_live_bus_the_monitor_sees_what_the_supervisor_books(tmp_path: Path) -> None:
    """Supervisor and emulated nodes on the virtual bus; the monitor only listens."""
    rig = Rig(tmp_path, [1, 2, 3], power_w=0.5)
    monitor_bus = can.Bus(interface="virtual", channel=rig.channel)
    model, lock = MonitorModel(Codec(), lost_after_s=30), threading.Lock()
    feed = LiveFeed(monitor_bus, model, lock)
    feed.start()
    try:
        service = rig.start_supervisor()
        rig.start_clients()
        rig.wait(lambda: all(rig.committed(n) >= 3 for n in (1, 2, 3)))
        rig.settle()
        status = service.status()

        def seen() -> dict[str, tuple[int, int, int]]:
            with lock:
                rows = model.snapshot(time.monotonic()).rows
            return {str(r.node): (r.commits, r.aborts, r.write_offs) for r in rows}

        booked = {
            name: (n["committed"], n["aborted"], n["written_off"])
            for name, n in status["nodes"].items()
        }
        rig.wait(lambda: seen() == booked)
        with lock:
            model.set_books(parse_status(status, time.monotonic(), "rig"))
            snap = model.snapshot(time.monotonic())
    finally:
        feed.stop()
        monitor_bus.shutdown()
        rig.close()
    for r in snap.rows:
        assert r.level_source == "telemetry" and not r.lost and r.alarms == 0
        assert r.books is not None and r.books.committed == r.commits >= 3
    assert snap.errors == {} and snap.books is not None
    assert snap.books.usable_uj == status["usable_uj"]


def test_a_receive_error_shows_until_frames_flow_again() -> None:
    model, lock = MonitorModel(Codec()), threading.Lock()
    listener = ModelListener(model, lock, clock=lambda: 1.0)
    listener.on_error(can.CanOperationError("adapter unplugged"))
    assert model.snapshot(1.0).notes == ("receive error: adapter unplugged",)
    listener.on_message_received(scenario.frames()[0])
    assert model.snapshot(1.0).notes == () and listener.received == 1


def test_a_socket_bus_gets_a_larger_receive_buffer() -> None:
    class SocketBus:  # what python-can's SocketcanBus exposes
        def __init__(self, sock: socket.socket) -> None:
            self.socket = sock

    a, b = socket.socketpair()
    with a, b:
        before = a.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        after = enlarge_receive_buffer(SocketBus(a), before * 4)  # type: ignore[arg-type]
        assert after is not None and after > before
    with can.Bus(interface="virtual", channel=uuid.uuid4().hex) as virtual:
        assert enlarge_receive_buffer(virtual) is None


# -- the screen loop -----------------------------------------------------------------------
class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


class BusFeed:
    """A bus as the screen loop sees it (``LiveFeed``'s states), the frames fed by the test."""

    def __init__(self) -> None:
        self.t = scenario.T0

    def start(self) -> None: ...
    def stop(self) -> None: ...
    def now(self) -> float:
        return self.t

    def pause(self, paused: bool) -> None: ...
    def step(self) -> None: ...
    def state(self, paused: bool) -> str:
        return "PAUSED (still counting)" if paused else "live"


def counts(lines: list[tuple[str, str]]) -> tuple[int, int]:
    """The frame counts in the title's corner and in the header line below it."""
    corner = re.search(r"([\d,]+) frames$", lines[0][0])
    header = re.match(r"frames ([\d,]+) ", lines[1][0])
    assert corner is not None and header is not None, lines[:2]
    return int(corner[1].replace(",", "")), int(header[1].replace(",", ""))


def test_pausing_a_replay_shows_one_frame_count_of_that_moment() -> None:
    """Issue 31: the header (the latest snapshot) and the corner (the replay's own count, read
    when painting) disagreed on a paused screen: 7,475 vs 7,720."""
    frames = scenario.frames()
    model, lock = MonitorModel(Codec()), threading.Lock()
    feed = ReplayFeed(iter(frames), model, lock, speed=1.0)
    display = Display(feed, model, lock, View(), Context("replay s.log", ""), 1.0, Clock())
    first = display.update([], 160, 30)  # a snapshot before the replay began
    assert first is not None and counts(first) == (0, 0)
    feed.start()
    try:
        deadline = time.monotonic() + 60
        while feed.fed < scenario.WRITE_OFF_AT and time.monotonic() < deadline:
            time.sleep(0.01)
        paused = display.update(["p"], 160, 30)  # no snapshot due: the clock stood still
        assert paused is not None and "replay x1 PAUSED" in paused[0][0]
        assert counts(paused) == (scenario.WRITE_OFF_AT, scenario.WRITE_OFF_AT)
        assert any(t.lstrip().startswith("5 ") and "INTENTION x3" in t for t, _ in paused)
    finally:
        feed.stop()


def test_a_paused_screen_is_redrawn_with_its_frozen_snapshot() -> None:
    """Issue 31: while paused the screen is still painted every refresh, after a resize and
    after the keys that change the view, from the snapshot taken when it was paused; the raw
    frames too, though the bus brought more since."""
    frames = scenario.frames()
    model, lock, clock, feed = MonitorModel(Codec()), threading.Lock(), Clock(), BusFeed()
    view = View()
    display = Display(feed, model, lock, view, Context("virtual", ""), 0.25, clock)

    def bus(upto: int) -> None:
        for f in frames[model.frames : upto]:
            feed.t = f.timestamp
            model.feed(f, f.timestamp)

    bus(scenario.WRITE_OFF_AT)
    assert display.update([], 160, 30) is not None
    clock.t += 0.1
    bus(scenario.WRITE_OFF_AT + 1)
    frozen = display.update(["p"], 160, 30)  # between two refreshes
    assert frozen is not None and frozen[0][0].endswith("PAUSED (still counting): 13 frames")
    assert counts(frozen) == (13, 13)
    bus(len(frames))  # the bus is still read and counted

    clock.t += 0.25
    again = display.update([], 160, 30)  # the periodic redraw
    assert again == frozen
    assert display.update([], 160, 30) is None  # nothing new within the period

    resized = display.update(["KEY_RESIZE"], 100, 20)
    assert resized is not None and len(resized) == 20 and counts(resized) == (13, 13)
    assert len(resized[0][0]) == 100 and all(len(t) <= 100 for t, _ in resized)

    by_level = display.update(["s"], 100, 20)
    assert by_level is not None and counts(by_level) == (13, 13)
    assert any(t.startswith("sort level  filter all  2 nodes") for t, _ in by_level)

    text = display.update(["/", "5", "\n"], 160, 30)
    assert text is not None and counts(text) == (13, 13)
    five = next(t for t, _ in text if t.lstrip().startswith("5 "))
    assert "write-off 0.300 J" in five and "commit" not in five  # tx 2's COMMITTED came after

    raw = display.update(["\n"], 160, 30)  # node 5's raw frames, as they were
    assert raw is not None
    head = next(t for t, _ in raw if t.startswith("raw frames of node 5"))
    assert head.endswith("the latest 4 of 4")
    assert sum("S->5" in t or "5->S" in t for t, _ in raw) == 4
    assert not any("COMMITTED" in t for t, _ in raw)
    clock.t += 0.25
    assert display.update([], 160, 30) == raw

    live = display.update(["p"], 160, 30)  # on again: what the bus brought meanwhile
    assert live is not None and counts(live) == (len(frames), len(frames))
    assert any(t.startswith("raw frames of node 5 on vcan0: the latest 7 of 7") for t, _ in live)


# -- the command line -----------------------------------------------------------------------
def test_once_prints_the_screen_of_a_whole_capture(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = scenario.write(tmp_path / "s.asc")
    assert main(["monitor", "--replay", str(log), "--once", "--bitrate", "500000"]) == 0
    out = capsys.readouterr().out
    assert "replay done: 17 frames" in out and "decode errors 1: crc 1" in out
    assert "0.630 J" in out and "q quit" not in out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--speed", "2"], "--speed and --fast pace a --replay"),
        (["--replay", "x.log", "-i", "virtual"], "not with --interface"),
        (["--replay", "x.log", "--status-file", "s.json"], "not with --replay"),
        (["--duration", "1s"], "--duration is for --once"),
        (["--replay", "missing.log", "--once"], "no such file"),
        ([], "needs a terminal"),
    ],
)
def test_bad_combinations_are_refused(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["monitor", *argv]) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--speed", "0"], "outside 0.01..1000"),
        (["--speed", "nan"], "outside 0.01..1000"),
        (["--nodes", "0-3"], "bad node range"),
        (["--sort", "age"], "invalid choice"),
        (["--replay", "x.log", "--speed", "2", "--fast"], "not allowed with"),
    ],
)
def test_bad_values_are_argparse_errors(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["monitor", *argv])
    assert exit_.value.code == 2 and message in capsys.readouterr().err
