"""`canergy monitor` driven as a person would: in a real terminal (tmux), keys sent with
`send-keys`, what the screen shows read with `capture-pane`.

scripts/test installs tmux where it is missing; a missing tmux fails here, it is not skipped.
Each test runs its own tmux server (a socket under tmp_path), so nothing else is touched.
"""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from support import monitor_scenario as scenario
from support.monitor_scenario import cell

TIMEOUT_S = 60.0
"""Longest wait for the screen to show something (a loaded 2-core CI machine)."""


class Terminal:
    """One tmux session, 160 x 50, running a command in a shell that reports its exit status."""

    def __init__(self, tmp: Path, command: list[str]) -> None:
        tmux = shutil.which("tmux")
        assert tmux is not None, "tmux is not installed (scripts/test installs it)"
        self.base = [tmux, "-S", str(tmp / "tmux.sock"), "-f", "/dev/null"]
        line = f"{shlex.join(command)}; echo EXIT=$?; sleep 600"
        env = "LANG=C.UTF-8 LC_ALL=C.UTF-8 TERM=screen-256color"
        subprocess.run(
            [*self.base, "new-session", "-d", "-s", "t", "-x", "160", "-y", "50", f"{env} {line}"],
            check=True,
            cwd=tmp,
        )

    def screen(self) -> str:
        return subprocess.run(
            [*self.base, "capture-pane", "-p", "-t", "t"],
            check=True,
            capture_output=True,
            text=True,
        ).stdout

    def keys(self, *keys: str, literal: bool = False) -> None:
        flags = ["-l"] if literal else []
        subprocess.run([*self.base, "send-keys", "-t", "t", *flags, *keys], check=True)

    def wait(self, what: str, shown: Callable[[str], bool]) -> str:
        """The first screen on which ``shown`` holds; fails with the last one after a minute."""
        deadline = time.monotonic() + TIMEOUT_S
        while True:
            text = self.screen()
            if shown(text):
                return text
            if time.monotonic() > deadline:
                raise AssertionError(f"the screen never showed {what}:\n{text}")
            time.sleep(0.1)

    def close(self) -> None:
        subprocess.run([*self.base, "kill-server"], check=False, capture_output=True)


@pytest.fixture
def terminal(tmp_path: Path) -> Iterator[Callable[[list[str]], Terminal]]:
    opened: list[Terminal] = []

    def start(command: list[str]) -> Terminal:
        opened.append(Terminal(tmp_path, command))
        return opened[-1]

    yield start
    for t in opened:
        t.close()


def canergy(*args: str) -> list[str]:
    return [sys.executable, "-m", "canergy", *args]


def lines(text: str) -> list[str]:
    return text.splitlines()


def header(text: str) -> str:
    return next(line for line in lines(text) if line.startswith("node "))


def node_row(text: str, node: int) -> str | None:
    return next((line for line in lines(text) if line.startswith(f"{node:>4} ")), None)


def column(text: str, node: int, title: str) -> str | None:
    row = node_row(text, node)
    return None if row is None else cell(header(text), row, title)


def test_replay_pause_step_filter_raw_frames_and_quit(
    tmp_path: Path, terminal: Callable[[list[str]], Terminal]
) -> None:
    capture = scenario.write(tmp_path / "story.log")
    t = terminal(canergy("monitor", "--replay", str(capture), "--bitrate", "500000"))

    # the first half-second of the capture plays at its own pace; then ten minutes of silence
    text = t.wait(
        "node 5's unanswered intention",
        lambda s: "INTENTION x3" in (node_row(s, 5) or "") and "decode errors 1: crc 1" in s,
    )
    three = node_row(text, 3)
    assert three is not None and "0.750 J" in three and "commit 0.500 J" in three
    assert column(text, 3, "returns") == "1" and "CRC 1" in three
    assert column(text, 5, "w/o") == "0" and "LOST" in (node_row(text, 5) or "")
    assert "foreign 1" in text and "of 500 kbit/s" in text

    # pause, then step one frame: node 5's next intention shows the write-off
    t.keys("p")
    text = t.wait("the pause", lambda s: "PAUSED" in lines(s)[0])
    assert column(text, 5, "w/o") == "0" and "n step" in lines(text)[-1]
    t.keys("n")
    text = t.wait("a write-off", lambda s: column(s, 5, "w/o") == "1")
    assert column(text, 5, "tx") == "2" and "write-off 0.300 J" in (node_row(text, 5) or "")

    # filter: node 3 only
    t.keys("/")
    t.wait("the filter prompt", lambda s: lines(s)[-1].startswith("filter nodes"))
    t.keys("3", literal=True)
    t.keys("Enter")
    text = t.wait("the filter applied", lambda s: "filter 3  1 of 2 nodes" in s)
    assert node_row(text, 3) is not None and node_row(text, 5) is None

    # the raw frames of the selected node (node 3, the only row), and back
    t.keys("Enter")
    text = t.wait("node 3's raw frames", lambda s: "raw frames of node 3 on vcan0" in s)
    assert re.search(
        r"0CE00D03 +\[8\] +B2 EE 02 00 00 00 00 00 +TELEMETRY +3->S +level 0\.750 J", text
    )
    assert "COMMITTED      3->S     tx 1  crc ok" in text and "CRC BAD" in text
    assert "INTENTION      S->5" not in text
    t.keys("Escape")
    t.wait("the table again", lambda s: node_row(s, 3) is not None)

    # play on to the end of the capture at its own pace
    t.keys("p")
    text = t.wait("the end of the replay", lambda s: "replay done: 17 frames" in s)
    assert "0.630 J" in (node_row(text, 3) or "")

    t.keys("q")
    text = t.wait("the monitor exit", lambda s: "EXIT=" in s)
    assert "EXIT=0" in text and "Traceback" not in text


def frame_counts(text: str) -> tuple[int, int] | None:
    """The frame counts in the title's corner and in the header line below it."""
    corner = re.search(r"([\d,]+) frames$", lines(text)[0].rstrip())
    header = re.match(r"frames ([\d,]+) ", lines(text)[1])
    if corner is None or header is None:
        return None
    return int(corner[1].replace(",", "")), int(header[1].replace(",", ""))


def test_an_empty_filter_and_a_paused_screen_redrawn(
    tmp_path: Path, terminal: Callable[[list[str]], Terminal]
) -> None:
    """Issue 31: ``/`` then Enter shows every node again; a paused screen is one moment (the
    header and the corner agree) and is redrawn after a resize and the keys that change it.
    A snapshot a minute apart: only keys and the pause paint a new screen in this test."""
    capture = scenario.write(tmp_path / "story.log")
    t = terminal(canergy("monitor", "--replay", str(capture), "--refresh", "60s"))
    t.wait("the first screen", lambda s: lines(s)[-1].startswith("q quit"))

    t.keys("/")
    t.wait("the filter prompt", lambda s: lines(s)[-1].startswith("filter nodes"))
    t.keys("3", literal=True)
    t.keys("Enter")
    t.wait("the filter applied", lambda s: lines(s)[3].startswith("sort node  filter 3  "))
    t.keys("/")
    t.wait("the filter prompt", lambda s: lines(s)[-1].startswith("filter nodes"))
    t.keys("Enter")  # nothing typed: every node
    t.wait("every node", lambda s: lines(s)[3].startswith("sort node  filter all  "))

    time.sleep(0.5)  # the replay reaches its ten-minute silence (the checks hold either way)
    t.keys("p")
    text = t.wait("the pause", lambda s: "PAUSED" in lines(s)[0] and frame_counts(s) is not None)
    counts = frame_counts(text)
    assert counts is not None and counts[0] == counts[1], lines(text)[:2]
    corner = lines(text)[0].rstrip()[-30:]

    subprocess.run([*t.base, "resize-window", "-t", "t", "-x", "120", "-y", "40"], check=True)
    text = t.wait(
        "the paused screen at 120 x 40",
        lambda s: (
            len(lines(s)) == 40
            and lines(s)[0].rstrip().endswith(corner)
            and len(lines(s)[0].rstrip()) == 120
            and lines(s)[-1].startswith("q quit")
        ),
    )
    assert frame_counts(text) == counts
    t.keys("s")
    text = t.wait("the sort by level", lambda s: lines(s)[3].startswith("sort level  "))
    assert frame_counts(text) == counts and len(lines(text)) == 40
    t.keys("Enter")
    text = t.wait("raw frames", lambda s: "raw frames of node" in s)
    raw = re.search(r"raw frames of node (\d+) on vcan0: the latest (\d+) of (\d+)", text)
    assert raw is not None and raw[2] == raw[3] and frame_counts(text) == counts
    node = int(raw[1])
    shown = [line for line in lines(text) if re.search(rf" S->{node} | {node}->S ", line)]
    assert len(shown) == int(raw[2]), text

    t.keys("Escape")
    t.wait("the table again", lambda s: lines(s)[3].startswith("sort level  "))
    t.keys("q")
    text = t.wait("the monitor exit", lambda s: "EXIT=" in s)
    assert "EXIT=0" in text and "Traceback" not in text


def test_live_bus_with_a_running_supervisor_s_books(
    tmp_path: Path, terminal: Callable[[list[str]], Terminal]
) -> None:
    """A real supervisor process with its control socket; the monitor on the same (empty)
    virtual bus shows the supervisor's books and its silent nodes as lost."""
    sock = tmp_path / "sup.sock"
    supervisor = subprocess.Popen(
        canergy(
            "supervisor", "-i", "virtual", "-c", "mon", "--nodes", "2-4", "--initial", "7J",
            "--state", str(tmp_path / "state.json"), "--control", str(sock), "--no-fsync",
        ),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + TIMEOUT_S
        while not sock.exists():
            assert supervisor.poll() is None, supervisor.communicate()[1]
            assert time.monotonic() < deadline, "the supervisor never opened its socket"
            time.sleep(0.1)
        t = terminal(canergy("monitor", "-i", "virtual", "-c", "mon", "--control", str(sock)))
        text = t.wait("the books", lambda s: "supervisor usable 7.000 J" in s)
        title = lines(text)[0].rstrip()
        assert "virtual mon" in title and title.endswith("live: 0 frames")
        for node in (2, 3, 4):
            row = node_row(text, node)
            assert row is not None and "| IDLE" in row and "0/0/0" in row and "LOST" in row
        assert node_row(text, 1) is None
        t.keys("q")
        assert "EXIT=0" in t.wait("the monitor exit", lambda s: "EXIT=" in s)
    finally:
        supervisor.terminate()
        supervisor.wait(timeout=30)
