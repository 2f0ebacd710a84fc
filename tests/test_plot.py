"""`canergy plot`: the data it draws (the audit's books over time) and the figure it writes."""

from __future__ import annotations

from pathlib import Path

import can
import pytest
from support import monitor_scenario as scenario

from canergy.cli import main
from canergy.codec import Codec
from canergy.inspect.audit import Auditor
from canergy.inspect.frames import describe
from canergy.inspect.timeline import timeline
from canergy.messages import Commit

PNG = b"\x89PNG\r\n\x1a\n"


def test_every_change_of_the_books_at_its_time() -> None:
    codec = Codec()
    tl = timeline([describe(codec, f) for f in scenario.frames()], samples=10**9)
    assert list(tl.nodes) == ["3", "5"] and tl.timed
    assert (tl.frames, tl.foreign, tl.end) == (17, 1, pytest.approx(600.5))
    three, five = tl.nodes["3"], tl.nodes["5"]
    assert three.times == pytest.approx([0.05, 0.08, 0.10, 0.11, 600.5])
    assert three.granted_uj == [0, 500_000, 500_000, 500_000, 500_000]  # COMMITTED at 0.08
    assert three.returned_uj == [0, 0, 0, 120_000, 120_000]  # RETURN_ACK at 0.11
    assert three.holdable_uj == [500_000, 500_000, 380_000, 380_000, 380_000]  # RETURN at 0.10
    assert five.times == pytest.approx([0.15, 600.0, 600.15, 600.5])
    assert five.granted_uj == [0, 0, 200_000, 200_000]  # the write-off is not a commit...
    assert five.holdable_uj == [300_000, 500_000, 500_000, 500_000]  # ...but the node may hold it
    assert three.alarms == five.alarms == [] and tl.violations == []
    damaged = [(m.kind, m.node, m.to_client) for m in tl.marks if m.damaged]
    assert damaged == [("ACK", "3", False)]
    assert len(tl.marks) == 16  # every canergy frame; not the CANopen heartbeat


def test_the_last_values_are_the_audit_s_whatever_the_sampling(tmp_path: Path) -> None:
    codec = Codec()
    described = [describe(codec, f) for f in scenario.frames()]
    coarse = timeline(described, samples=3)
    auditor = Auditor()
    for d in described:
        auditor.feed(d)
    report = auditor.report()["nodes"]
    for name, s in coarse.nodes.items():
        assert s.times[-1] == coarse.end
        assert s.granted_uj[-1] == report[name]["granted_uj"]
        assert s.returned_uj[-1] == report[name]["returned_uj"]
        assert s.holdable_uj[-1] == report[name]["holdable_max_uj"]
    assert len(coarse.nodes["3"].times) < 5


def test_forgeries_become_alarms_on_their_node() -> None:
    codec = Codec()
    frames = scenario.frames()
    ident, data = codec.encode(Commit(5, 9, 1000))  # for a tx never on the bus
    forged = can.Message(
        timestamp=scenario.T0 + 1, arbitration_id=ident, data=data, channel="vcan0"
    )
    frames.insert(12, forged)
    tl = timeline([describe(codec, f) for f in frames])
    assert tl.nodes["5"].alarms == [pytest.approx(1.0)] and len(tl.violations) == 1


def test_plot_writes_a_figure(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capture = scenario.write(tmp_path / "story.blf")
    out = tmp_path / "story.png"
    assert main(["plot", str(capture), "-o", str(out)]) == 0
    assert out.read_bytes()[:8] == PNG and out.stat().st_size > 20_000
    assert "node 3, node 5" in capsys.readouterr().out
    svg = tmp_path / "five.svg"
    assert main(["plot", str(capture), "-o", str(svg), "--node", "5", "--to", "1s"]) == 0
    assert b"<svg" in svg.read_bytes()[:400]


def test_a_demo_capture_plots(tmp_path: Path) -> None:
    log = tmp_path / "demo.log"
    assert main(["demo", "--seed", "3", "--log", str(log)]) == 0
    assert main(["plot", str(log), "-o", str(tmp_path / "demo.png"), "--node", "2-3"]) == 0
    assert (tmp_path / "demo.png").read_bytes()[:8] == PNG


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["missing.log", "-o", "f.png"], "no such file"),
        (["story.log", "-o", "f.xyz"], "unknown figure format"),
        (["story.log", "-o", "nodir/f.png"], "no directory"),
        (["story.log", "-o", "f.png", "--node", "9"], "none of these nodes in the capture"),
        (["story.log", "-o", "f.png", "--from", "2s", "--to", "1s"], "--to must be after --from"),
        (["story.log", "-o", "f.png", "--from", "10000s"], "nothing of it in that window"),
        (["foreign.log", "-o", "f.png"], "no canergy frames among its 1 frame(s)"),
    ],
)
def test_clear_errors(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    argv: list[str],
    message: str,
) -> None:
    monkeypatch.chdir(tmp_path)
    scenario.write(tmp_path / "story.log")
    (tmp_path / "foreign.log").write_text("(1.000000) can0 701#05\nnot a frame\n")
    assert main(["plot", *argv]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "f.png").exists()
