"""The host's end of a guarded drive (``DriveLink``) against the emulated drive on python-can's
virtual bus: what its worker thread writes first."""

from __future__ import annotations

import time
import uuid
from collections.abc import Iterator

import can
import pytest

from canergy.cia402.guard import CW_DISABLE_VOLTAGE, Command, VerifyCommand
from canergy.live.canopen.cia402_link import DriveLink, LinkConfig
from canergy.live.runtime import monotonic_us
from firmware_model.drive.canopen_face import DriveFace, drive_network
from firmware_model.drive.live_bench import DRIVE, wait_for
from firmware_model.drive.model import EDS as DRIVE_EDS
from firmware_model.drive.model import DriveModel

READ_S = 0.05
"""Each of the link's SDO reads made this slow: a loaded venue's round trip (user-mode Linux)."""


@pytest.fixture
def link() -> Iterator[DriveLink]:
    channel = f"cia402-link-{uuid.uuid4().hex}"
    model = DriveModel(DRIVE, monotonic_us())
    drive_net = drive_network(can.Bus(interface="virtual", channel=channel))
    face = DriveFace(model, drive_net)
    face.boot()
    face.start()
    host_net = drive_network(can.Bus(interface="virtual", channel=channel))
    out = DriveLink(host_net, DRIVE, LinkConfig(eds=DRIVE_EDS), monotonic_us)
    try:
        wait_for(lambda: out.ready_at is not None)
        yield out
    finally:
        out.close()
        face.close()
        for net in (drive_net, host_net):
            if net.notifier is not None:
                net.notifier.stop()
            if net.bus is not None:
                net.bus.shutdown()


def test_a_stop_goes_out_during_a_read_back_not_after_it(
    link: DriveLink, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A periodic read-back reads every object of the PDO configuration (28 SDO transfers on
    the emulated drive, a hundred on a drive with four PDOs each way); in user-mode Linux, beside
    an application's SDO writes, that took seconds, and a stop decided meanwhile waited for all
    of it: its reaction (5.3 s) went into the bound, which then exceeded a 2 J budget at every
    taper level, so the drive was never enabled. The stop is written before the read-back's
    next transfer."""
    reads: list[int] = []
    slow_read = link._read

    def read(index: int, sub: int) -> int:
        reads.append(index)
        time.sleep(READ_S)
        return slow_read(index, sub)

    monkeypatch.setattr(link, "_read", read)
    assert link.setup is not None
    keys = tuple(link.setup.config)
    assert len(keys) > 20, "the read-back this test needs is long"
    link.command(VerifyCommand(1, keys, "periodic read-back", monotonic_us()))
    wait_for(lambda: len(reads) >= 3)
    decided = monotonic_us()
    link.command(Command(CW_DISABLE_VOLTAGE, "budget exhausted", decided))
    wait_for(lambda: link.commands_sent == 1, timeout=30)
    assert not link.drain_verified(), "the stop waited for the whole read-back"
    assert link.last_command is not None
    assert link.last_command["controlword"] == CW_DISABLE_VOLTAGE
    # one read in progress at most, and the write itself: not the read-back's 20-odd reads
    assert link.reaction_max_us < 10 * READ_S * 1e6, link.last_command
    wait_for(lambda: link.verified, timeout=60)  # the read-back still completes, afterwards
    ((seq, read_back),) = link.drain_verified()
    assert seq == 1 and all(v is not None for v in read_back.values())
