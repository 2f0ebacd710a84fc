"""The moteus link's diagnostic-stream exchange (``canergy.live.devices.moteus_link``) against a
scripted controller on a bus object of our own: an answer that comes after the guard gave up on
its line is not taken for the next line's."""

from __future__ import annotations

from collections import deque
from typing import Any

import can

from canergy.devices.moteus import (
    DIAGNOSTIC_CHANNEL,
    Poll,
    Stream,
    can_id,
    conf_set,
    decode,
    encode,
)
from canergy.live.devices.moteus_link import MoteusLink, MoteusLinkConfig

SERVO, SOURCE = 1, 0x7E


class ScriptedBus(can.BusABC):  # type: ignore[misc]
    """Answers each poll of the guard with the next of ``answers`` (b"": nothing to say)."""

    def __init__(self, answers: list[bytes]) -> None:
        self.answers = deque(answers)
        self.link: MoteusLink | None = None
        self.channel_info = "scripted"
        self._filters = None

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        subframes, _ = decode(bytes(msg.data))
        if self.link is None or not any(isinstance(s, Poll) for s in subframes):
            return
        data = self.answers.popleft() if self.answers else b""
        reply = encode(Stream(True, DIAGNOSTIC_CHANNEL, data))
        frame = can.Message(arbitration_id=can_id(SERVO, SOURCE), data=reply, is_fd=True)
        self.link.on_message_received(frame)

    def _recv_internal(self, timeout: float | None) -> tuple[Any, bool]:
        return None, False


def link(answers: list[bytes]) -> MoteusLink:
    bus = ScriptedBus(answers)
    config = MoteusLinkConfig(source=SOURCE, answer_timeout_s=0.05)
    made = MoteusLink(bus, SERVO, config, None, lambda: 0)
    bus.link = made
    return made


def test_a_late_answer_is_drained_not_taken_for_the_next_lines() -> None:
    # nothing for the first line's polls until it is given up on, then its answer, late
    quiet = [b""] * 1000
    m = link(quiet)
    assert m._ask(b"conf get servo.max_power_W\n") is None and m.late
    bus = m.bus
    assert isinstance(bus, ScriptedBus)
    bus.answers = deque([b"100.000000\r\n", b"", b"OK\r\n"])
    assert m._answered(conf_set("servo.max_power_W", 100.0), lambda a: a == "OK")
    assert not m.events and not m.late  # no foreign write reported: the late answer was drained


def test_an_answer_not_the_lines_is_a_write_behind_the_guard() -> None:
    m = link([b"7.000000\r\n"])
    assert not m._answered(conf_set("servo.max_power_W", 100.0), lambda a: a == "OK")
    assert len(m.events) == 1  # the guard is told: stopped for good
