"""canergy decode / audit: candump text, every python-can log format, garbage, forged frames."""

from __future__ import annotations

import json
from pathlib import Path

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from canergy.cli import main
from canergy.codec import Codec, DecodeErrorReason
from canergy.demo import DemoConfig, run_demo
from canergy.faults import FaultProfile
from canergy.inspect.audit import Auditor
from canergy.inspect.captures import parse_line, read_file, read_text
from canergy.inspect.frames import describe
from canergy.messages import Commit, Intention

DATA = Path(__file__).parent / "data"
CLEAN = DATA / "two-nodes.log"
CODEC = Codec()


@pytest.mark.parametrize(
    ("text", "ident", "data", "remote"),
    [
        ("(1700000000.000100) vcan0 0CE00901#0B0100", 0x0CE00901, "0B0100", False),
        ("(1700000000.000100) vcan0 0CE00901#0B0100 R", 0x0CE00901, "0B0100", False),
        ("  vcan0  0CE00901   [3]  0B 01 00", 0x0CE00901, "0B0100", False),
        ("(1700000000.000100)  can0  701   [1]  05", 0x701, "05", False),
        ("  vcan0  0CE0090A   [0]  remote request", 0x0CE0090A, "", True),
        ("(1700000000.000100) vcan0 123#R", 0x123, "", True),
    ],
)
def test_candump_formats_parse(text: str, ident: int, data: str, remote: bool) -> None:
    frame = parse_line(text)
    assert (frame.arbitration_id, bytes(frame.data).hex().upper(), frame.is_remote_frame) == (
        ident,
        data,
        remote,
    )


@given(st.text(max_size=80))
def test_any_line_is_a_frame_or_reported_garbage(text: str) -> None:
    garbage: list[int] = []
    frames = list(read_text([text], lambda n, line, why: garbage.append(n)))
    assert len(frames) + len(garbage) == (1 if text.strip() else 0)


def test_garbage_lines_are_reported_with_their_number(capsys: pytest.CaptureFixture[str]) -> None:
    lines = [*CLEAN.read_text().splitlines()[:2], "hello", "(1.0) vcan0 0CE00901#0B01Z0", ""]
    bad: list[tuple[int, str]] = []
    frames = list(read_text(lines, lambda n, line, why: bad.append((n, why))))
    assert len(frames) == 2 and [n for n, _ in bad] == [3, 4]


def test_decoding_matches_the_golden_output(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["decode", str(CLEAN), "--color", "never"]) == 0
    assert capsys.readouterr().out == (DATA / "two-nodes.decoded").read_text()


def _events(path: Path) -> list[tuple[object, ...]]:
    out = []
    for frame in read_file(path, lambda *a: pytest.fail(f"garbage in {path}: {a}")):
        d = describe(CODEC, frame)
        out.append((d.arbitration_id, d.data, d.message, d.crc_ok))
    return out


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".csv", ".trc", ".log"])
def test_every_python_can_format_decodes_to_the_same_events(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"capture{suffix}"
    with can.Logger(str(path)) as writer:
        for frame in read_file(CLEAN, lambda *a: None):
            writer.on_message_received(frame)
    assert _events(path) == _events(CLEAN) and len(_events(CLEAN)) == 16


def test_an_unreadable_capture_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "x.blf"
    bad.write_bytes(b"not a blf file at all")
    assert main(["decode", str(bad)]) == 2
    assert "cannot read" in capsys.readouterr().err
    assert main(["audit", str(tmp_path / "x.pcap")]) == 2
    assert "unknown capture format" in capsys.readouterr().err


def test_audit_agrees_with_the_run_that_made_the_capture(tmp_path: Path) -> None:
    log = tmp_path / "run.log"
    quiet = FaultProfile(loss=0, duplicate=0, reorder=0, corrupt=0)
    result = run_demo(DemoConfig(nodes=(1, 2, 3), transactions=60, faults=quiet, resets=0, log=log))
    auditor = Auditor(initial=result.config.initial)
    for frame in read_file(log, lambda *a: None):
        auditor.feed(describe(CODEC, frame))
    auditor.finish()
    report = auditor.report()
    assert report["passive"], report["violations"]
    for node, stats in result.nodes.items():
        assert report["nodes"][str(node)]["committed"] == stats.committed


def _write(path: Path, frames: list[can.Message]) -> None:
    with can.Logger(str(path)) as writer:
        for f in frames:
            writer.on_message_received(f)


def _frame(msg: Commit | Intention, t: float) -> can.Message:
    ident, data = CODEC.encode(msg)
    # on the capture's own bus: the audit keeps each channel's nodes apart
    return can.Message(timestamp=t, arbitration_id=ident, data=data, channel="virtual0")


@pytest.mark.parametrize(
    ("forged", "what"),
    [(Commit(1, 1, 0), "COMMIT for tx 1 after tx 2 began"), (None, "replayed old INTENTION tx 1")],
)
def test_a_forged_commit_or_replayed_intention_fails_the_audit(
    tmp_path: Path, forged: Commit | None, what: str, capsys: pytest.CaptureFixture[str]
) -> None:
    frames = list(read_file(CLEAN, lambda *a: None))
    first = describe(CODEC, frames[0]).message
    assert isinstance(first, Intention) and first.node == 1
    if isinstance(forged, Commit):
        forged = Commit(1, 1, first.amount_mj)
    injected = _frame(forged or first, frames[-1].timestamp + 0.001)
    path = tmp_path / "forged.log"
    _write(path, [*frames, injected])
    assert main(["audit", str(CLEAN)]) == 0
    capsys.readouterr()
    assert main(["audit", str(path), "--json"]) == 1
    report = json.loads(capsys.readouterr().out)
    (violation,) = report["violations"]
    assert violation["frame"] == len(frames) + 1 and what in violation["what"]


def test_the_paper_variant_creating_energy_is_flagged(tmp_path: Path) -> None:
    log = tmp_path / "paper.log"
    assert main(["demo", "--variant", "paper", "--seed", "5", "--log", str(log)]) == 1
    argv = ["audit", str(log), "--reordered", "--json"]
    assert main(argv) == 1


def test_dump_shows_live_frames_like_candump(capsys: pytest.CaptureFixture[str]) -> None:
    import threading
    import uuid

    channel = f"dump-{uuid.uuid4().hex}"
    frames = list(read_file(CLEAN, lambda *a: None))[:3]
    result: list[int] = []
    argv = ["dump", "-i", "virtual", "-c", channel, "-n", "4", "--json", "--nodes", "1-2"]
    thread = threading.Thread(target=lambda: result.append(main(argv)))
    thread.start()
    with can.Bus(interface="virtual", channel=channel) as bus:
        import time

        from can.interfaces.virtual import channels

        deadline = time.monotonic() + 30
        while len(channels.get(channel, [])) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)  # until dump has opened its end of the channel
        for frame in [
            *frames,
            can.Message(arbitration_id=0x701, is_extended_id=False, data=b"\x05"),
        ]:
            bus.send(frame)
        thread.join(timeout=30)
    assert result == [0]
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [x["type"] for x in lines] == ["INTENTION", "INTENTION", "ACK"]  # 0x701 filtered out
    assert all(x["crc_ok"] for x in lines)


def test_a_damaged_frame_that_claims_nothing_valid_is_shown_not_fatal() -> None:
    ident = CODEC.arbitration_id(Commit.TYPE, 1)
    frame = can.Message(arbitration_id=ident, data=bytes(5))  # zero amount and a wrong CRC
    d = describe(CODEC, frame)
    assert d.message is None and d.crc_ok is False and d.problem == DecodeErrorReason.BAD_CRC.value


def test_a_capture_starting_mid_transaction_is_not_flagged() -> None:
    frames = list(read_file(CLEAN, lambda *a: None))
    auditor = Auditor()
    for frame in frames[5:]:  # the first intentions and ACKs happened before the capture
        auditor.feed(describe(CODEC, frame))
    auditor.finish()
    assert auditor.report()["passive"], auditor.report()["violations"]
