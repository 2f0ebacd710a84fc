"""Detection without a key: a second supervisor and a spoofer are reported within a second.

A side never receives its own frames back (SocketCAN and python-can's virtual bus alike), so a
frame in its own direction for a node it handles was sent by someone else.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from support.intrusion_bench import CODEC, Bench, bench

from canergy.messages import Ack, Intention


def test_watch_filters_pass_the_own_direction_too() -> None:
    intention, _ = CODEC.encode(Intention(5, 1, 1, 0))
    ack, _ = CODEC.encode(Ack(5, 1))
    other_ack, _ = CODEC.encode(Ack(6, 1))
    assert not CODEC.accepts(CODEC.supervisor_filters(), intention, True)
    assert CODEC.accepts(CODEC.supervisor_watch_filters(), intention, True)
    assert not CODEC.accepts(CODEC.client_filters(5), ack, True)
    assert CODEC.accepts(CODEC.client_watch_filters(5), ack, True)
    assert not CODEC.accepts(CODEC.client_watch_filters(5), other_ack, True)


@pytest.fixture
def warned(tmp_path: Path) -> Iterator[Bench]:
    yield from bench(tmp_path)


def test_a_second_supervisor_is_reported_within_a_second(warned: Bench) -> None:
    b = warned
    sent = b.forge(Intention(1, 500, 100, 0))
    b.wait(lambda: b.status().get("intrusions", 0) >= 1)
    report = b.status()["intrusion_report"]
    assert report["first_at_us"] - sent < 1_000_000
    (event,) = report["recent"]
    assert event["node"] == 1 and event["frame"].startswith("0CE00101#")
    assert b.status()["nodes"]["1"]["intrusions"] == 1
    assert not b.status()["stopping"]  # warn: counted and reported, nothing else
    b.forge(Intention(7, 1, 100, 0))  # a node this supervisor does not manage: not its business
    time.sleep(0.3)
    assert b.status()["intrusions"] == 1


def test_a_frame_in_a_nodes_name_is_reported_by_the_node(warned: Bench) -> None:
    b = warned
    node = b.host.nodes[1]
    sent = b.forge(Ack(1, 321))
    b.wait(lambda: node.intrusions.total >= 1)
    assert node.intrusions.first_at is not None and node.intrusions.first_at - sent < 1_000_000
    assert node.status()["intrusions"] == 1
    assert node.status()["intrusion_report"]["recent"][0]["frame"].startswith("0CE00901#")


def test_stop_on_intrusion_ends_the_supervisor_with_status_3(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for b in bench(tmp_path, "--on-intrusion", "stop"):
        b.forge(Intention(1, 500, 100, 0))
        assert b.sup.stop() == 3
        final = b.status()
        assert final["stopped_by_intrusion"] and final["intrusions"] >= 1
    assert "stopped on intrusion" in capsys.readouterr().err
