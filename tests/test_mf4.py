"""ASAM MDF4 captures (python-can's `mf4` extra, asammdf): decode, audit, plot and monitor read an
.mf4 file written by python-can's MF4Writer exactly as the same frames in candump's format."""

from __future__ import annotations

import json
from pathlib import Path

import can
import pytest
from support import monitor_scenario as scenario

from canergy.cli import main
from canergy.codec import Codec
from canergy.inspect import captures
from canergy.inspect.captures import CaptureError, read_file
from canergy.inspect.frames import describe
from canergy.inspect.timeline import timeline

pytestmark = pytest.mark.mf4  # run in .venv-mf4 (scripts/test): asammdf slows every `import can`


@pytest.fixture
def both(tmp_path: Path) -> tuple[Path, Path]:
    """The story as candump text and as MF4."""
    return scenario.write(tmp_path / "story.log"), scenario.write(tmp_path / "story.mf4")


def _json_lines(text: str) -> list[dict[str, object]]:
    rows = [json.loads(line) for line in text.splitlines()]
    for row in rows:
        row.pop("channel")  # MF4 numbers its bus channels: vcan0 comes back as 0
    return rows


def test_the_frames_come_back_unchanged(both: tuple[Path, Path]) -> None:
    log, mf4 = both
    text, binary = list(read_file(log, print)), list(read_file(mf4, print))
    assert len(binary) == len(text) == 17
    for a, b in zip(text, binary, strict=True):
        assert a.equals(b, timestamp_delta=1e-6, check_channel=False)


def test_decode_and_audit(both: tuple[Path, Path], capsys: pytest.CaptureFixture[str]) -> None:
    log, mf4 = both
    outputs = []
    for path in (log, mf4):
        assert main(["decode", str(path), "--json"]) == 0
        decoded = _json_lines(capsys.readouterr().out)
        assert main(["audit", str(path), "--json"]) == 0
        outputs.append((decoded, json.loads(capsys.readouterr().out)))
    assert outputs[0] == outputs[1]
    decoded, report = outputs[1]
    assert [d["type"] for d in decoded][:4] == ["TELEMETRY", "INTENTION", "ACK", "COMMIT"]
    assert report["nodes"]["5"]["granted_uj"] == 200_000 and report["passive"]


def test_plot_and_monitor(
    both: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    mf4 = both[1]
    codec = Codec()
    series = [timeline([describe(codec, f) for f in read_file(p, print)]).nodes for p in both]
    assert series[0] == series[1] and series[1]["5"].holdable_uj[-1] == 500_000
    assert main(["plot", str(mf4), "-o", str(tmp_path / "story.png")]) == 0
    assert (tmp_path / "story.png").read_bytes()[:4] == b"\x89PNG"
    assert main(["monitor", "--replay", str(mf4), "--once"]) == 0
    out = capsys.readouterr().out
    assert "replay done: 17 frames" in out and "0.630 J" in out


def test_without_asammdf_the_error_says_what_to_install(
    both: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(can.io.mf4, "asammdf", None)
    with pytest.raises(CaptureError, match=r"pip install 'canergy\[mf4\]'"):
        list(captures.read_file(both[1], print))
