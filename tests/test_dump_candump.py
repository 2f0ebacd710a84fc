"""``canergy dump`` for users of can-utils' candump: -l/--log, -t a|d|z|A, CHANNEL,FILTER
arguments, CAN FD without --fd, the line saying what it waits on; and ``canergy supervisor
--listen-only``'s one-line status. All on python-can's virtual bus, in this process."""

from __future__ import annotations

import json
import os
import re
import signal
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from datetime import datetime
from pathlib import Path
from typing import Any

import can
import pytest
from can.interfaces.virtual import VirtualBus, channels

import canergy.cli.dump
from canergy.cli import main
from canergy.codec import Codec
from canergy.inspect.candump import CandumpFilter, ChannelFilters, log_line
from canergy.live.supervisor.control import request
from canergy.messages import Ack, Intention, Message, Telemetry

CODEC = Codec()
T0 = 1_700_000_000.0
WAIT_S = 30.0
"""How long a test waits for what must happen (a loaded machine is slow, never this slow)."""


def _channel() -> str:
    return f"candump-{uuid.uuid4().hex[:12]}"


def _frame(msg: Message, at: float | None = None, **extra: Any) -> can.Message:
    ident, data = CODEC.encode(msg)
    return can.Message(
        arbitration_id=ident, is_extended_id=True, data=data, timestamp=at or 0.0, **extra
    )


def _raw(ident: int, data: bytes = b"\x05", at: float | None = None, **extra: Any) -> can.Message:
    extended = extra.pop("is_extended_id", ident > 0x7FF)
    return can.Message(
        arbitration_id=ident, is_extended_id=extended, data=data, timestamp=at or 0.0, **extra
    )


N1 = [
    _frame(Intention(1, 1, 2000, 0), T0),
    _frame(Ack(1, 1), T0 + 0.25),
    _frame(Intention(2, 1, 1000, 0), T0 + 1.5),
    _frame(Ack(2, 1), T0 + 1.500001),
]
"""Frames of nodes 1 and 2, 0.25 s, 1.25 s and 1 µs apart."""


def _until(done: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    while not done():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.005)


def _opened(channel: str, count: int = 2) -> Callable[[], bool]:
    return lambda: len(channels.get(channel, [])) >= count


def dump(
    argv: Sequence[str],
    frames: Sequence[can.Message],
    channel: str,
    *,
    timestamps: bool = True,
) -> int:
    """``canergy dump argv`` in a thread while ``frames`` are sent on ``channel`` (with their
    own timestamps, or the time they are sent); its exit status."""
    result: list[int] = []
    thread = threading.Thread(target=lambda: result.append(main(["dump", *argv])), daemon=True)
    with VirtualBus(channel=channel, preserve_timestamps=timestamps) as bus:
        thread.start()
        _until(lambda: _opened(channel)() or not thread.is_alive(), "dump to open its bus")
        for frame in frames:
            bus.send(frame)
        thread.join(timeout=WAIT_S)
    assert not thread.is_alive(), "dump did not end"
    return result[0]


@pytest.fixture
def opened_with(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, Any]]:
    """The keyword arguments of every ``can.Bus`` opened (python-can's ``can.cli`` opens the
    bus through it); the test's own end of a channel is a ``VirtualBus``, not counted."""
    real = can.Bus
    seen: list[dict[str, Any]] = []

    def spy(**config: Any) -> can.BusABC:
        seen.append(dict(config))
        return real(**config)

    monkeypatch.setattr(can, "Bus", spy)
    return seen


# --- -l and --log ----------------------------------------------------------------------------


def test_l_logs_every_frame_to_candumps_file_name_read_back_by_python_can_and_decode(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    channel = _channel()
    fd = _raw(0x0CE00105, bytes(range(12)), T0 + 2, is_fd=True, bitrate_switch=True)
    remote = _raw(0x123, b"", T0 + 3, is_remote_frame=True, dlc=2)
    frames = [*N1, _raw(0x701, b"\x05", T0 + 1.75), fd, remote]
    before = datetime.now().replace(microsecond=0)
    argv = ["-i", "virtual", "-c", channel, "-l", "--nodes", "1", "-n", str(len(frames))]
    assert dump(argv, frames, channel) == 0
    after = datetime.now()
    out, err = capsys.readouterr()
    (log,) = tmp_path.glob("*")
    assert re.fullmatch(r"candump-\d{4}-\d\d-\d\d_\d{6}\.log", log.name), log.name
    assert before <= datetime.strptime(log.name, "candump-%Y-%m-%d_%H%M%S.log") <= after
    assert f"canergy dump: logging every frame received to {log.name}\n" in err
    assert len(out.splitlines()) == 2  # --nodes 1 hides the rest from the view, not the log
    lines = log.read_text().splitlines()
    first = bytes(N1[0].data).hex().upper()
    assert lines[0] == f"(1700000000.000000) {channel} 0CE00101#{first}"
    assert lines[4] == f"(1700000001.750000) {channel} 701#05"
    assert lines[5] == f"(1700000002.000000) {channel} 0CE00105##1000102030405060708090A0B"
    assert lines[6] == f"(1700000003.000000) {channel} 123#R2"
    read = list(can.LogReader(str(log)))
    assert [(m.arbitration_id, bytes(m.data), m.is_extended_id) for m in read[:6]] == [
        (f.arbitration_id, bytes(f.data), f.is_extended_id) for f in frames[:6]
    ]
    assert [m.timestamp for m in read] == pytest.approx([f.timestamp for f in frames], abs=1e-6)
    assert read[5].is_fd and read[5].bitrate_switch and not read[4].is_fd
    assert read[6].is_remote_frame and all(m.channel == channel for m in read)
    assert main(["decode", str(log), "--json"]) == 0
    decoded = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [d["type"] for d in decoded[:4]] == ["INTENTION", "ACK", "INTENTION", "ACK"]
    assert all(d["crc_ok"] for d in decoded[:4]) and decoded[4]["id"] == "701"
    assert [d["dlc"] for d in decoded[5:]] == [12, 0]


def test_l_twice_in_one_second_keeps_both_files(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    stamp = datetime(2026, 11, 27, 3, 30, 0)
    monkeypatch.setattr(canergy.cli.dump, "datetime", type("Fixed", (), {"now": lambda: stamp}))
    for frame in N1[:2]:
        channel = _channel()
        assert dump(["-i", "virtual", "-c", channel, "-l", "-n", "1"], [frame], channel) == 0
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["candump-2026-11-27_033000-2.log", "candump-2026-11-27_033000.log"]
    assert [len((tmp_path / n).read_text().splitlines()) for n in names] == [1, 1]


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".csv", ".trc", ".log.gz"])
def test_log_writes_the_format_its_extension_names(
    suffix: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    channel = f"{_channel()}-1234567"  # BLF cannot hold channel 1234568: written without
    path = tmp_path / f"capture{suffix}"
    assert dump(["-i", "virtual", "-c", channel, "--log", str(path), "-n", "4"], N1, channel) == 0
    assert f"logging every frame received to {path}" in capsys.readouterr().err
    read = list(can.LogReader(str(path)))
    assert [(m.arbitration_id, bytes(m.data)) for m in read] == [
        (f.arbitration_id, bytes(f.data)) for f in N1
    ]


def test_a_log_is_closed_on_ctrl_c(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """In the main thread, as from a terminal: SIGINT ends the dump and the BLF file (written
    out only when closed) holds every frame."""
    channel = _channel()
    path = tmp_path / "ctrl-c.blf"
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}

    def send() -> None:
        with VirtualBus(channel=channel, preserve_timestamps=True) as bus:
            _until(_opened(channel), "dump to open its bus")
            for frame in N1:
                bus.send(frame)
            queues = channels[channel]
            _until(lambda: all(q.qsize() == 0 for q in queues), "dump to read every frame")
            os.kill(os.getpid(), signal.SIGINT)

    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    try:
        assert main(["dump", "-i", "virtual", "-c", channel, "--log", str(path)]) == 0
    finally:
        for number, handler in handlers.items():
            signal.signal(number, handler)
        sender.join(timeout=WAIT_S)
    assert len(capsys.readouterr().out.splitlines()) == 4
    assert [m.arbitration_id for m in can.LogReader(str(path))] == [f.arbitration_id for f in N1]


def test_a_log_is_closed_when_the_bus_fails(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "failed.blf"
    frames = iter(N1[:2])

    class Failing(can.BusABC):
        def __init__(self) -> None:
            super().__init__(channel="failing")

        def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
            frame = next(frames, None)
            if frame is None:
                raise can.CanOperationError("the adapter went away")
            return frame, False

        def send(self, msg: can.Message, timeout: float | None = None) -> None:
            raise NotImplementedError

    monkeypatch.setattr(canergy.cli.dump, "open_bus", lambda args, filters: Failing())
    with pytest.raises(can.CanOperationError):
        main(["dump", "-i", "virtual", "-c", "failing", "--log", str(path)])
    assert [m.arbitration_id for m in can.LogReader(str(path))] == [
        f.arbitration_id for f in N1[:2]
    ]


@pytest.mark.parametrize(
    ("log", "says"),
    [
        ("missing/x.log", "no such directory"),
        ("x.xyz", "unknown log format '.xyz'"),
        ("noext", "no extension to name its format"),
        ("x.blf.gz", "cannot compress .blf"),
    ],
)
def test_a_log_that_cannot_be_written_is_one_line_before_the_bus_opens(
    log: str,
    says: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    opened_with: list[dict[str, Any]],
) -> None:
    argv = ["dump", "-i", "virtual", "-c", _channel(), "--log", str(tmp_path / log)]
    assert main(argv) == 2
    out, err = capsys.readouterr()
    (line,) = err.splitlines()
    assert not out and line.startswith("canergy dump: error: --log ") and says in line, line
    assert opened_with == [] and list(tmp_path.iterdir()) == []


def test_a_log_that_is_no_regular_file_is_refused_and_a_directory_gets_candumps_name(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    os.mkfifo(tmp_path / "pipe.log")
    argv = ["dump", "-i", "virtual", "-c", _channel(), "--log", str(tmp_path / "pipe.log")]
    assert main(argv) == 2
    assert "not a regular file" in capsys.readouterr().err
    (tmp_path / "pipe.log").unlink()
    channel = _channel()
    assert (
        dump(["-i", "virtual", "-c", channel, "--log", str(tmp_path), "-n", "1"], N1, channel) == 0
    )
    (log,) = tmp_path.iterdir()
    assert log.name.startswith("candump-") and len(log.read_text().splitlines()) == 1


# --- -t --------------------------------------------------------------------------------------


def _stamped(capsys: pytest.CaptureFixture[str], *mode: str) -> list[str]:
    """The lines of a dump of ``N1`` with these -t flags, its channel's name shown as CH."""
    channel = _channel()
    assert dump(["-i", "virtual", "-c", channel, *mode, "-n", "4"], N1, channel) == 0
    return [x.replace(channel, "CH") for x in capsys.readouterr().out.splitlines()]


def test_t_modes_stamp_like_candump_and_keep_the_alignment(
    capsys: pytest.CaptureFixture[str],
) -> None:
    lines = {mode: _stamped(capsys, "-t", mode) for mode in ("a", "d", "z", "A")}
    stamps = {mode: [x.split(")")[0] + ")" for x in got] for mode, got in lines.items()}
    assert stamps["a"] == [
        "(1700000000.000000)",
        "(1700000000.250000)",
        "(1700000001.500000)",
        "(1700000001.500001)",
    ]
    assert stamps["d"] == ["(000.000000)", "(000.250000)", "(001.250000)", "(000.000001)"]
    assert stamps["z"] == ["(000.000000)", "(000.250000)", "(001.500000)", "(001.500001)"]
    local = [datetime.fromtimestamp(T0 + s) for s in (0, 0, 1, 1)]
    micros = ["000000", "250000", "500000", "500001"]
    assert stamps["A"] == [
        f"({t:%Y-%m-%d %H:%M:%S}.{u})" for t, u in zip(local, micros, strict=True)
    ]
    for mode, got in lines.items():  # every line as it is with -t a, after the stamp
        assert [x[len(s) :] for x, s in zip(got, stamps[mode], strict=True)] == [
            x[len(s) :] for x, s in zip(lines["a"], stamps["a"], strict=True)
        ], mode
    assert _stamped(capsys) == lines["a"]  # -t a is the default


# --- CHANNEL,FILTER -------------------------------------------------------------------------


def _shown(
    argv: list[str], frames: list[can.Message], channel: str, count: int, capsys: Any
) -> list[str]:
    assert dump([*argv, "-n", str(count), "--json"], frames, channel) == 0
    return [json.loads(x)["id"] for x in capsys.readouterr().out.splitlines()]


@pytest.mark.parametrize(
    ("filters", "frames", "shown"),
    [
        # 29-bit: canergy's INTENTIONs (the 11-bit 0x101 has the same low bits)
        ("0CE00100:1FFFFF00", [0x0CE00201, 0x101, 0x0CE00101, 0x0CE00901], ["0CE00101"]),
        # 11-bit, as candump: the 11 bits under the mask, in 11-bit and 29-bit frames
        ("123:7FF", [0x124, 0x0CE00124, 0x123, 0x0CE00123], ["123", "0CE00123"]),
        # inverted: everything but canergy's INTENTIONs
        ("0CE00100~1FFFFF00", [0x0CE00101, 0x0CE00201, 0x123], ["0CE00201", "123"]),
        # every canergy frame of node 5
        (
            "0CE00005:1FFFF0FF",
            [0x0CE00106, 0x005, 0x0CE00105, 0x0CE00905],
            ["0CE00105", "0CE00905"],
        ),
        # several: any one passes
        ("701:7FF,0CE00900:1FFFFF00", [0x702, 0x0CE00101, 0x701, 0x0CE00902], ["701", "0CE00902"]),
        # j: every one must pass
        ("0CE00000:1FFFF000,001:0FF,j", [0x0CE00102, 0x001, 0x0CE00201], ["0CE00201"]),
        # the kernel's flags: 92345678:DFFFFFFF is extended id 12345678, not remote
        ("92345678:DFFFFFFF", [0x12345679, 0x12345678], ["12345678"]),
    ],
)
def test_candump_filters_pass_and_drop(
    filters: str, frames: list[int], shown: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    channel = _channel()
    sent = [_raw(i, is_extended_id=i > 0x7FF) for i in frames]
    argv = ["-i", "virtual", f"{channel},{filters}"]
    assert _shown(argv, sent, channel, len(shown), capsys) == shown


def test_filters_go_to_the_interface_and_are_checked_again(
    capsys: pytest.CaptureFixture[str],
    opened_with: list[dict[str, Any]],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    channel = _channel()
    frames = [_raw(0x0CE00201), _raw(0x0CE00101)]
    argv = ["-i", "virtual", f"{channel},0CE00100:1FFFFF00"]
    assert _shown(argv, frames, channel, 1, capsys) == ["0CE00101"]
    (config,) = opened_with
    assert config["can_filters"] == [
        {"can_id": 0x0CE00100, "can_mask": 0x1FFFFF00, "extended": True}
    ]
    assert config["channel"] == channel
    # an interface that filters nothing (python-can's software filter off): dump still does
    monkeypatch.setattr(can.BusABC, "_matches_filters", lambda self, msg: True)
    channel = _channel()
    argv = ["-i", "virtual", f"{channel},0CE00100:1FFFFF00"]
    assert _shown(argv, frames, channel, 1, capsys) == ["0CE00101"]
    # inverted filters cannot go to python-can: none there, all in dump
    channel = _channel()
    argv = ["-i", "virtual", f"{channel},0CE00200~1FFFFF00"]
    assert _shown(argv, frames, channel, 1, capsys) == ["0CE00101"]
    assert opened_with[-1]["can_filters"] == []


def test_the_positional_channel_is_c(capsys: pytest.CaptureFixture[str]) -> None:
    channel = _channel()
    assert _shown(["-i", "virtual", "-c", channel, channel], [N1[0]], channel, 1, capsys) == [
        "0CE00101"
    ]
    assert main(["dump", "-i", "virtual", "-c", "other", channel]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line == f"canergy dump: error: two channels: -c other and {channel}; give one"


@pytest.mark.parametrize(
    ("text", "named"),
    [
        ("vcan0,12G:7FF", "'12G:7FF'"),
        ("vcan0,123", "'123'"),
        ("vcan0,123:7FF:1", "'123:7FF:1'"),
        ("vcan0,123456789:7FF", "'123456789:7FF'"),
        ("vcan0,", "''"),
        (",123:7FF", "no channel name"),
        ("vcan0,#FFFFFFFF", "error frame filters (#ERRMASK) are not supported"),
    ],
)
def test_a_bad_filter_is_one_argparse_error_naming_it(
    text: str, named: str, capsys: pytest.CaptureFixture[str], opened_with: list[dict[str, Any]]
) -> None:
    with pytest.raises(SystemExit) as ended:
        main(["dump", "-i", "virtual", text])
    assert ended.value.code == 2
    (line,) = [x for x in capsys.readouterr().err.splitlines() if "error:" in x]
    assert line.startswith("canergy dump: error: argument CHANNEL[,FILTER...]: ") and named in line
    assert opened_with == []


def test_filter_rules_as_candump_reads_them() -> None:
    eff = CandumpFilter.parse("0CE00100:1FFFFF00")
    assert eff.as_python_can() == {"can_id": 0x0CE00100, "can_mask": 0x1FFFFF00, "extended": True}
    assert CandumpFilter.parse("800:7FF").as_python_can()["extended"] is True  # above 0x7FF
    assert CandumpFilter.parse("0123:7FF").as_python_can()["extended"] is True  # 4 digits
    assert "extended" not in CandumpFilter.parse("123:7FF").as_python_can()
    assert CandumpFilter.parse("0x123:0x7FF") == CandumpFilter.parse("123:7FF")
    spec = ChannelFilters.parse("can0,123:7FF,200~700")
    assert spec.channel == "can0" and len(spec.filters) == 2 and spec.hardware() == []
    error = can.Message(is_error_frame=True, arbitration_id=0x4)
    assert spec.accepts(error) and ChannelFilters.parse("can0,0:1FFFFFFF").accepts(error)
    remote = _raw(0x123, b"", is_remote_frame=True)
    assert not ChannelFilters.parse("can0,123:C00007FF").accepts(remote)
    assert ChannelFilters.parse("can0,123:C00007FF").accepts(_raw(0x123))


# --- CAN FD, and the line saying where dump waits ---------------------------------------------


def test_fd_frames_are_seen_without_fd(
    capsys: pytest.CaptureFixture[str], opened_with: list[dict[str, Any]]
) -> None:
    channel = _channel()
    fd = _raw(0x0CE00105, bytes(range(64)), T0, is_fd=True, bitrate_switch=True)
    assert dump(["-i", "virtual", "-c", channel, "-n", "1"], [fd], channel) == 0
    out, err = capsys.readouterr()
    assert opened_with[0]["fd"] is True and "FD" not in err
    assert "  0CE00105   [64]  00 01 02 " in out
    channel = _channel()  # --fd is still accepted, and changes nothing
    assert dump(["-i", "virtual", "-c", channel, "--fd", "-n", "1"], [fd], channel) == 0
    assert opened_with[1]["fd"] is True and "[64]" in capsys.readouterr().out


def test_an_interface_that_refuses_fd_is_opened_classic_with_one_line(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    real = can.Bus
    tried: list[bool] = []

    def classic_only(**config: Any) -> can.BusABC:
        tried.append(bool(config.get("fd")))
        if config.get("fd"):
            raise can.CanInitializationError("this adapter does not do CAN FD")
        return real(**config)

    monkeypatch.setattr(can, "Bus", classic_only)
    channel = _channel()
    assert dump(["-i", "virtual", "-c", channel, "-n", "1"], [N1[0]], channel) == 0
    out, err = capsys.readouterr()
    assert tried == [True, False] and len(out.splitlines()) == 1
    (line,) = [x for x in err.splitlines() if "FD" in x]
    assert line.startswith(f"canergy dump: virtual {channel} did not open for CAN FD (this adapter")
    assert "FD frames will not be seen" in line and "--data-bitrate" in line


def test_a_bus_that_opens_neither_way_is_the_usual_one_line_error(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(**config: Any) -> can.BusABC:
        raise can.CanInitializationError(f"no adapter (fd={bool(config.get('fd'))})")

    monkeypatch.setattr(can, "Bus", broken)
    assert main(["dump", "-i", "virtual", "-c", _channel()]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line == "canergy dump: error: cannot open the CAN bus: no adapter (fd=False)"


def test_monitor_opens_its_bus_for_fd_too(
    capsys: pytest.CaptureFixture[str], opened_with: list[dict[str, Any]]
) -> None:
    argv = ["monitor", "-i", "virtual", "-c", _channel(), "--once", "--duration", "10ms"]
    assert main(argv) == 0
    assert [c["fd"] for c in opened_with] == [True]


def test_dump_says_where_it_waits_before_any_frame(capsys: pytest.CaptureFixture[str]) -> None:
    channel = _channel()
    err: list[str] = []
    result: list[int] = []
    argv = ["dump", "-i", "virtual", "-c", channel, "-n", "1"]
    thread = threading.Thread(target=lambda: result.append(main(argv)), daemon=True)
    with VirtualBus(channel=channel) as bus:
        thread.start()

        def said() -> bool:
            err.append(capsys.readouterr().err)
            return "waiting" in "".join(err)

        _until(said, "the waiting line")
        bus.send(N1[0])
        thread.join(timeout=WAIT_S)
    assert result == [0]
    assert "".join(err).splitlines() == [f"canergy dump: waiting on {channel} (virtual)..."]


# --- supervisor --listen-only ------------------------------------------------------------------


@pytest.fixture
def supervisor(tmp_path: Path) -> Iterator[Callable[..., tuple[int, str]]]:
    """``canergy supervisor ARGS`` on a fresh virtual channel in a thread, fed TELEMETRY of node
    2 until its stdout says so (``until``), then stopped on its control socket: (exit, stdout)."""
    threads: list[threading.Thread] = []

    def run(*extra: str, until: Callable[[str], bool], capsys: Any) -> tuple[int, str]:
        channel = _channel()
        control = tmp_path / "c.sock"
        argv = ["supervisor", "-i", "virtual", "-c", channel, "--nodes", "1-3", "--control"]
        argv += [str(control), "--status-period", "20ms", *extra]
        result: list[int] = []
        thread = threading.Thread(target=lambda: result.append(main(argv)), daemon=True)
        threads.append(thread)
        seen: list[str] = []
        with VirtualBus(channel=channel) as bus:
            thread.start()
            _until(lambda: control.exists(), "the control socket")

            def heard() -> bool:
                bus.send(_frame(Telemetry(2, 1500)))
                seen.append(capsys.readouterr().out)
                return until("".join(seen))

            _until(heard, "the status to show node 2")
            request(control, {"stop": True}, WAIT_S)
            thread.join(timeout=WAIT_S)
        seen.append(capsys.readouterr().out)
        return result[0], "".join(seen)

    yield run
    for thread in threads:
        thread.join(timeout=WAIT_S)


LISTENING = re.compile(
    r"listening on candump-\w+: \d+ frames, nodes talking (none|2), silent (1-3|1,3), levels "
    r"(0\.000|1\.500) J, decode errors 0, intrusions 0(, stopping)?"
)


def test_listen_only_prints_one_line_per_status(
    supervisor: Callable[..., tuple[int, str]], capsys: pytest.CaptureFixture[str]
) -> None:
    code, out = supervisor(
        "--listen-only",
        until=lambda text: "talking 2, silent 1,3, levels 1.500 J" in text or "1500000" in text,
        capsys=capsys,
    )
    assert code == 0
    lines = out.splitlines()
    assert lines and all(LISTENING.fullmatch(x) for x in lines), lines[:3]
    # no books of its own: a level reported above them is no intrusion (it was, every one)
    assert all("intrusions 0" in x for x in lines), lines


def test_listen_only_keeps_json_for_its_status_file(
    supervisor: Callable[..., tuple[int, str]], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    status = tmp_path / "status.json"

    def heard(text: str) -> bool:
        return (
            status.exists()
            and json.loads(status.read_text())["nodes"]["2"]["level_uj"] == 1_500_000
        )

    code, out = supervisor(
        "--listen-only", "--status-file", str(status), until=heard, capsys=capsys
    )
    assert code == 0 and out == ""


def test_a_supervisor_that_sends_keeps_json_lines(
    supervisor: Callable[..., tuple[int, str]], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    def heard(text: str) -> bool:
        return '"level_uj": 1500000' in text

    state = ["--state", str(tmp_path / "s.json"), "--initial", "1J", "--no-fsync"]
    code, out = supervisor(*state, until=heard, capsys=capsys)
    assert code == 0
    assert all(json.loads(x)["role"] == "supervisor" for x in out.splitlines())


def test_log_line_as_candump_writes_it() -> None:
    frame = _raw(0x0CE00101, b"\x01\x02", 1.5)
    assert log_line(frame, "can0") == "(0000000001.500000) can0 0CE00101#0102\n"
    fd = _raw(0x123, bytes(9), 2.0, is_fd=True, error_state_indicator=True, is_extended_id=False)
    assert log_line(fd, "can1") == "(0000000002.000000) can1 123##2" + "00" * 9 + "\n"


def test_an_error_frame_logged_as_candump_writes_it_is_read_back_as_one() -> None:
    """candump -l writes an error frame's id with SocketCAN's error flag (0x20000000): the
    capture readers took it for an identifier beyond 29 bits and skipped the line."""
    from canergy.inspect.captures import parse_line

    error = can.Message(
        is_error_frame=True, arbitration_id=0x4, data=bytes([0, 4, 0, 0, 0, 0, 0, 0])
    )
    back = parse_line(log_line(error, "can0"))
    assert back.is_error_frame and back.arbitration_id == 0x4 and back.data == error.data
    with pytest.raises(ValueError, match="beyond 29 bits"):
        parse_line("(1.000000) can0 40000004#00")  # no flag canergy knows
