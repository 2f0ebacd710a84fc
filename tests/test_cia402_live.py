"""``canergy supervisor --cia402`` on python-can's virtual bus, against the emulated drive (a
python-canopen ``LocalNode``) and a canergy node, with an independent python-canopen master as
the application (``firmware_model.drive.live_bench``). Wall clock, generous timeouts; the bound
is the guard's own, with the reaction and latency it measured in the same run.
"""

from __future__ import annotations

import json
import re
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from canergy.cli import main
from canergy.devices.proxy import HELD
from canergy.ledger import ledger_from_status
from canergy.live.runtime import monotonic_us
from canergy.live.supervisor.control import request
from firmware_model.drive.live_bench import (
    DRIVE,
    NODE,
    Bench,
    app_read,
    exhausted,
    guarded_bench,
    wait_for,
)


@pytest.fixture
def exhausting(tmp_path: Path) -> Iterator[Bench]:
    """4 J in all: the drive and the canergy node are topped up to 2 J until it is gone. On
    the compiled core: the node's frames take its frame path beside the drive's proxy."""
    with guarded_bench(tmp_path, 10, "--initial", "4J", "--target", "2J", "--core", "c") as bench:
        yield bench


@pytest.fixture
def plenty(tmp_path: Path) -> Iterator[Bench]:
    """200 J, topped up to 20 J; TPDOs may pause for 1 s (a loaded host stalls threads for
    300 ms: at the default 100 ms a late TPDO stopped the drive for good), the bound 15.4 J at
    that gap. The periodic read-back runs (one answered after the guard's own limits write that
    followed it was once taken for a write behind the guard: fixed in 2a09f84)."""
    flags = ("--initial", "200J", "--target", "20J")
    with guarded_bench(tmp_path, 10, *flags, gap_ms=1000) as bench:
        yield bench


def test_the_budget_runs_out_and_the_drive_stops_inside_the_bound(
    exhausting: Bench, capsys: pytest.CaptureFixture[str]
) -> None:
    b = exhausting
    wait_for(lambda: exhausted(b), timeout=120)
    told = capsys.readouterr().err  # the supervisor says when the guard stops a drive
    assert "canergy supervisor: drive 10: stopped (budget exhausted; " in told
    assert "OPERATION ENABLED" in [s for _, s in b.model.psm.history]

    def standing() -> bool:  # a coasting stop: the load and friction bring it to rest
        with b.face.lock:
            return abs(b.model.velocity_rad_s) < 0.05

    wait_for(standing)
    # an independent master reads the drive's objects alongside the guard (the drive has one
    # SDO server for both, and the guard re-reads its configuration at any time: tried again)
    wait_for(lambda: (d := b.drive_status()) and d["limits_confirmed"])
    assert app_read(b.app, 0x6041) & 0x4F == 0x40  # SWITCH ON DISABLED
    assert abs(app_read(b.app, 0x606C)) < 50
    final = b.stop()
    books = final["nodes"][str(DRIVE)]
    granted = books["delivered_uj"] - books["returns_credited_uj"]
    drive = final["cia402"]["drives"][str(DRIVE)]
    # the proxy's books: what was granted was spent on what the meter saw, or is still held
    assert drive["credited_uj"] == granted == drive["spent_uj"] + drive["usable_uj"]
    assert drive["meter"] == "counter"
    assert b.drawn() <= granted + drive["bound_uj"]
    # the ledger over the supervisor, the canergy node and the drive's proxy
    assert final["conservation"]["holds"] and final["usable_uj"] == 0
    node_books = final["nodes"][str(NODE)]
    assert granted + node_books["delivered_uj"] == final["initial_uj"]
    books = ledger_from_status(final, [b.node_host.nodes[NODE].status()])
    assert books.passive and books.spent >= drive["spent_uj"], books
    # the node's answers went through the compiled core's frame path, not around it
    assert final["frame_path"] == "c" and final["frame_path_frames"] > 0


def held(reason: str | None) -> bool:
    return (reason or "").startswith(HELD)


def test_the_proxy_leg_is_captured_and_audits_clean(
    exhausting: Bench, capsys: pytest.CaptureFixture[str]
) -> None:
    b = exhausting
    # stopped with its budget gone, or held with too little left to run until a stop (a loaded
    # machine's timings raise what it needs: seen once with the vcan suite running beside)
    wait_for(
        lambda: (
            exhausted(b)
            or ((d := b.drive_status()) and d["guard"] == "stopped" and held(d["stop_reason"]))
        ),
        timeout=120,
        show=b.drive_status,
    )
    books = b.stop()["nodes"][str(DRIVE)]
    capsys.readouterr()
    assert main(["audit", str(b.tmp / "proxy.log")]) == 0
    out = capsys.readouterr().out
    row = re.search(rf"^\s+{DRIVE}\s+\d+\s+(\d+)\s+\d+\s+\d+\s+\d+\s+([\d.]+)", out, re.M)
    assert row is not None, out
    assert int(row[1]) == books["committed"] > 0
    assert round(float(row[2]) * 1e6) == books["delivered_uj"]


def test_top_ups_keep_the_drive_running(plenty: Bench) -> None:
    b = plenty
    wait_for(lambda: b.model.state == "OPERATION ENABLED", show=b.drive_status)
    time.sleep(3)  # about 3 W for 3 s: top-ups of 0.5 J each (--max-grant)
    drive = b.drive_status()
    assert drive is not None and drive["stops"] == 0 and drive["guard"] == "running", drive
    history = [s for _, s in b.model.psm.history]
    assert history[history.index("OPERATION ENABLED") :] == ["OPERATION ENABLED"]
    drawn = b.drawn()  # before the status: the books only grow meanwhile
    final = b.status()
    assert final is not None
    books = final["nodes"][str(DRIVE)]
    assert books["committed"] >= 3
    # topped up ahead of its needs, it never even reached the end of what it was granted
    assert drawn <= books["delivered_uj"]


def _eds_without(tmp_path: Path, index: int) -> Path:
    """The emulator's EDS without object ``index`` (0x6080: a drive that has no speed limit to
    write; 0x6076: one whose set-up keeps failing)."""
    from firmware_model.drive.model import EDS as DRIVE_EDS

    text = DRIVE_EDS.read_text()
    start = text.index(f"[{index:04X}]")
    text = text[:start] + text[text.index("\n[", start) + 1 :]
    listed = re.search(rf"(\d+)=0x{index:04X}\n", text)
    assert listed is not None
    text = text.replace(listed[0], "")  # its entry in the object list goes too (renumbered)
    lines, n = [], 0
    section = ""
    for line in text.splitlines():
        if line.startswith("["):
            section = line
        if section == "[OptionalObjects]" and re.match(r"\d+=0x", line):
            n += 1
            line = f"{n}={line.split('=', 1)[1]}"
        elif section == "[OptionalObjects]" and line.startswith("SupportedObjects="):
            line = "SupportedObjects=@"
        lines.append(line)
    path = tmp_path / f"no-{index:04X}.eds"
    path.write_text("\n".join(lines).replace("SupportedObjects=@", f"SupportedObjects={n}", 1))
    return path


ENVELOPE = (
    *("--cia402-meter", "envelope", "--cia402-max-torque", "265"),
    *("--cia402-max-current", "265", "--cia402-max-speed", "100500"),
)


@pytest.mark.parametrize(
    ("flags", "eds_without", "said"),
    [
        (
            ("--cia402-meter", "sampled-electrical", "--cia402-bus-current", "0x2012"),
            None,
            ("cannot be guarded", "0x2012", "drive 10"),
        ),
        (ENVELOPE, 0x6080, ("cannot be guarded", "0x6080", "drive 10")),
        (ENVELOPE, 0x6076, ("set-up failed, retrying",)),
    ],
    ids=["tpdos-lack-the-current", "no-speed-limit-to-write", "set-up-keeps-failing"],
)
def test_a_drive_the_guard_cannot_meter_is_disabled(
    tmp_path: Path, flags: tuple[str, ...], eds_without: int | None, said: tuple[str, ...]
) -> None:
    """Its TPDOs lack the object sampled-electrical metering needs, or it has no 0x6080 to take
    the envelope's speed limit: the guard refuses it, names the drive and the object in the
    status, and disables the drive the application had enabled. One whose set-up keeps failing
    (no 0x6076 to read) is disabled at every attempt meanwhile."""
    import threading
    import uuid

    import can
    import canopen

    from canergy.live.canopen.cia402_link import EDS
    from firmware_model.drive.canopen_face import DriveFace, drive_network
    from firmware_model.drive.model import EDS as DRIVE_EDS
    from firmware_model.drive.model import DriveModel

    channel = f"cia402-bad-{uuid.uuid4().hex}"
    eds = DRIVE_EDS if eds_without is None else _eds_without(tmp_path, eds_without)
    model = DriveModel(DRIVE, monotonic_us(), eds=eds)  # the face advances it on its clock
    drive_net = drive_network(can.Bus(interface="virtual", channel=channel))
    face = DriveFace(model, drive_net)
    face.boot()
    face.start()
    app_bus = can.Bus(interface="virtual", channel=channel)
    app_net = canopen.Network(app_bus)
    app_net.notifier = can.Notifier(app_bus, list(app_net.listeners), 0.1)
    app = canopen.RemoteNode(DRIVE, str(EDS))
    app.sdo.RESPONSE_TIMEOUT = 2.0
    app_net.add_node(app)
    result: list[int] = []
    argv = [
        "supervisor",
        *("-i", "virtual", "-c", channel, "--cia402", str(DRIVE), "--initial", "1J"),
        *("--state", str(tmp_path / "s.json"), "--no-fsync", "--status-period", "50ms"),
        *("--status-file", str(tmp_path / "status.json"), "--control", str(tmp_path / "c")),
        *flags,
    ]
    try:
        for controlword in (0x06, 0x07, 0x0F):
            app.sdo[0x6040].raw = controlword
        wait_for(lambda: model.state == "OPERATION ENABLED")
        thread = threading.Thread(target=lambda: result.append(main(argv)), daemon=True)
        thread.start()
        wait_for(lambda: model.state == "SWITCH ON DISABLED", timeout=60)

        def refused() -> bool:
            try:
                status = json.loads((tmp_path / "status.json").read_text())
            except (FileNotFoundError, json.JSONDecodeError):
                return False
            error = status["cia402"]["drives"][str(DRIVE)]["error"] or ""
            return all(part in error for part in said)

        wait_for(refused)
        request(tmp_path / "c", {"stop": True}, 30)
        thread.join(timeout=60)
        assert result == [0]
    finally:
        face.close()
        for net in (drive_net, app_net):
            if net.notifier is not None:
                net.notifier.stop()
            if net.bus is not None:
                net.bus.shutdown()


@pytest.mark.parametrize("mode", ["counter", "envelope"])
def test_pulses_between_tpdos_on_the_virtual_bus_stay_inside_grant_plus_bound(
    tmp_path: Path, mode: str
) -> None:
    """The issue's pulses, from an application master on the wall clock: target velocity up and
    down every 10 ms at 10,000 rad/s² with 20 ms TPDOs, until the budget runs out (or 20 s)."""
    from firmware_model.drive.live_bench import app_write

    with guarded_bench(
        tmp_path, 20, "--initial", "2J", "--target", "2J", with_node=False, mode=mode
    ) as b:
        app_write(b.app, 0x6083, 10_000_000)
        app_write(b.app, 0x6084, 10_000_000)
        end = time.monotonic() + 20
        high = True
        while time.monotonic() < end and not exhausted(b):
            app_write(b.app, 0x60FF, 100_000 if high else 0)
            high = not high
            time.sleep(0.01)
        final = b.stop()
    drive = final["cia402"]["drives"][str(DRIVE)]
    books = final["nodes"][str(DRIVE)]
    granted = books["delivered_uj"] - books["returns_credited_uj"]
    assert drive["meter"] == mode and drive["bound_uj"] is not None
    assert b.drawn() <= granted + drive["bound_uj"]
    # all charged but what the drive drew after the guard's last reading, as the supervisor
    # stopped: a count, and the 15.07 W envelope over a TPDO period, a reaction and a latency
    t = drive["bound_timings_us"]
    after_last = 1_000 + 15.07 * (20_000 + t["reaction"] + t["latency"])
    assert drive["metered_uj"] >= min(b.drawn(), granted) - after_last


def test_the_exit_disables_the_drive_and_meters_what_its_link_still_holds_before_the_last_status(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The supervisor's loop is held off (its passes run no guard: a loaded host) while the
    application reverses the drive from 100 rad/s, its TPDOs waiting in the link's queue; then the
    supervisor is told to stop. Its exit disables the drive (by SDO: answered before the link
    closes) and charges the envelope over the time held, up to the drive's latency past the
    halt, before it writes the last status. It once wrote that status first, the drive still
    enabled and nothing charged since the hold, and disabled it after."""
    from canergy.live.canopen.cia402_host import GuardedSupervisor
    from canergy.live.supervisor.service import SupervisorService
    from firmware_model.drive.live_bench import app_write

    held, holding = threading.Event(), threading.Event()
    handlers: list[GuardedSupervisor] = []
    wake = GuardedSupervisor.on_wakeup
    write = SupervisorService.write_status
    states_at_writes: list[str] = []

    def held_off(handler: GuardedSupervisor, now: int) -> Any:
        if handler not in handlers:
            handlers.append(handler)
        if held.is_set():
            holding.set()
            return ()
        return wake(handler, now)

    def written(service: SupervisorService) -> None:
        if held.is_set():  # the bench is up
            with b.face.lock:
                states_at_writes.append(b.model.state)
        write(service)

    monkeypatch.setattr(GuardedSupervisor, "on_wakeup", held_off)
    monkeypatch.setattr(SupervisorService, "write_status", written)
    flags = ("--initial", "200J", "--target", "20J")
    with guarded_bench(tmp_path, 10, *flags, with_node=False, mode="envelope", gap_ms=1000) as b:
        wait_for(lambda: b.model.state == "OPERATION ENABLED", show=b.drive_status)
        wait_for(lambda: (d := b.drive_status()) and d["guard"] == "running", timeout=60)
        wait_for(lambda: b.model.velocity_rad_s > 50, timeout=60)  # the guard's taper opened
        (handler,) = handlers
        guard, link = handler.guarded.drives[DRIVE]
        held.set()
        wait_for(holding.is_set, timeout=30)
        metered, start = guard.metering.metered_uj, b.drawn()
        app_write(b.app, 0x60FF, -100_000)  # reversing: 0.2 s at the acceleration's torque
        wait_for(  # 0.1 J, not charged yet
            lambda: b.drawn() - start > 100_000,
            timeout=30,
            show=lambda: (b.model.state, b.drawn() - start, guard.phase, guard.stop_reason),
        )
        assert link.pending()  # TPDOs waiting to be taken in
        final = b.stop()
        drawn = b.drawn()
    drive = final["cia402"]["drives"][str(DRIVE)]
    print(
        f"held: drawn {drawn - start} µJ, metered {drive['metered_uj'] - metered} µJ; guard "
        f"{drive['guard']}, drive {states_at_writes[-1]}"
    )
    assert states_at_writes[-1] != "OPERATION ENABLED", states_at_writes[-3:]
    assert drive["stop_reason"] == "supervisor stopping"
    assert drive["metered_uj"] - metered >= drawn - start
    assert final["conservation"]["holds"]
