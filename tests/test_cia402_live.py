"""``canergy supervisor --cia402`` on python-can's virtual bus, against the emulated drive (a
python-canopen ``LocalNode``) and a canergy node, with an independent python-canopen master as
the application. Wall clock, generous timeouts; the bound uses the times measured in the run.
"""

from __future__ import annotations

import json
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import canopen
import pytest
from live_rig import Loop

from canergy.cia402.meter import overshoot_bound_uj
from canergy.cli import main
from canergy.codec import Codec
from canergy.live.cia402_link import EDS
from canergy.live.control import request
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.messages import Direction
from firmware_model.actuator import PowerProfile
from firmware_model.drive.canopen_face import DriveFace, drive_network
from firmware_model.drive.model import DriveModel
from firmware_model.drive.motor import LoadTorque
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore

DRIVE, NODE, APP = 10, 1, 5
PDO_MS = 10


def wait_for(condition: Callable[[], Any], timeout: float = 60.0) -> Any:
    end = time.monotonic() + timeout
    while not (value := condition()):
        assert time.monotonic() < end, "timed out"
        time.sleep(0.02)
    return value


@dataclass
class Bench:
    tmp: Path
    channel: str
    model: DriveModel
    face: DriveFace
    app: canopen.RemoteNode
    status_path: Path
    control: Path
    result: list[int]
    thread: threading.Thread
    node_host: NodeHost

    def status(self) -> dict[str, Any] | None:
        try:
            return dict(json.loads(self.status_path.read_text()))
        except (FileNotFoundError, json.JSONDecodeError):
            return None

    def drive_status(self) -> dict[str, Any] | None:
        status = self.status()
        return None if status is None else dict(status["cia402"]["drives"][str(DRIVE)])

    def drawn(self) -> int:
        with self.face.lock:
            return self.model.drawn_uj


def start(tmp: Path, *supervisor_args: str) -> Iterator[Bench]:
    channel = f"cia402-{uuid.uuid4().hex}"
    now = monotonic_us()
    model = DriveModel(
        DRIVE,
        now,
        load=LoadTorque.constant(0.02, opposing=True),
        defaults={(0x1800 + i, 5): PDO_MS for i in range(3)},
    )
    drive_net = drive_network(can.Bus(interface="virtual", channel=channel))
    face = DriveFace(model, drive_net)
    face.boot()
    face.start()
    node = FirmwareNode(
        NODE,
        NvStore(tmp / "1.nv", NODE, fsync=False),
        NodeConfig(power=PowerProfile.constant(0.2), telemetry_period_us=100_000),
        now,
    )
    node_host = NodeHost([node])
    node_loop = Loop(
        BusRuntime(
            can.Bus(interface="virtual", channel=channel),
            node_host,
            codec=Codec(),
            receives=Direction.TO_CLIENT,
        )
    )
    app_net = canopen.Network(can.Bus(interface="virtual", channel=channel))
    app_net.notifier = can.Notifier(app_net.bus, list(app_net.listeners), 0.1)
    app = canopen.RemoteNode(DRIVE, str(EDS))
    app.sdo.RESPONSE_TIMEOUT = 2.0
    app_net.add_node(app)
    status, control = tmp / "status.json", tmp / "ctl.sock"
    argv = [
        "supervisor",
        *("-i", "virtual", "-c", channel),
        *("--nodes", str(NODE), "--cia402", str(DRIVE)),
        *("--state", str(tmp / "s.json"), "--no-fsync"),
        *("--status-file", str(status), "--status-period", "50ms"),
        *("--control", str(control)),
        *("--max-grant", "500mJ", "--response-timeout", "100ms"),
        *("--cia402-resistance", "1", "--cia402-enable"),
        *("--cia402-capture", str(tmp / "proxy.log")),
        *supervisor_args,
    ]
    result: list[int] = []
    thread = threading.Thread(target=lambda: result.append(main(argv)), daemon=True)
    thread.start()
    bench = Bench(tmp, channel, model, face, app, status, control, result, thread, node_host)
    try:
        wait_for(lambda: (d := bench.drive_status()) and d["ready"])
        # the application: profile velocity at 100 rad/s; the guard enables the drive
        app.sdo[0x6060].raw = 3
        app.sdo[0x6083].raw = 1_000_000
        app.sdo[0x60FF].raw = 100_000
        yield bench
    finally:
        if thread.is_alive() and control.exists():
            request(control, {"stop": True}, 30)
        thread.join(timeout=60)
        node_loop.halt()
        face.close()
        for net in (drive_net, app_net):
            assert net.notifier is not None
            net.notifier.stop()
            net.bus.shutdown()


@pytest.fixture
def exhausting(tmp_path: Path) -> Iterator[Bench]:
    """2 J in all: the drive and the canergy node are topped up to 1 J until it is gone."""
    yield from start(tmp_path, "--initial", "2J", "--target", "1J")


@pytest.fixture
def plenty(tmp_path: Path) -> Iterator[Bench]:
    yield from start(tmp_path, "--initial", "100J", "--target", "1J")


def stop_time_us(model: DriveModel) -> int:
    """From quick stop to no power: the drive's own history."""
    history = model.psm.history
    start = next(t for t, s in history if s == "QUICK STOP ACTIVE")
    return next(t for t, s in history if t > start and s != "QUICK STOP ACTIVE") - start


def test_the_budget_runs_out_and_the_drive_stops_inside_the_bound(exhausting: Bench) -> None:
    b = exhausting
    drive = wait_for(
        lambda: (d := b.drive_status()) and d["stop_reason"] == "budget exhausted" and
        d["guard"] == "stopped" and d["drive_state"] == "SWITCH ON DISABLED" and d,
        timeout=120,
    )
    assert "OPERATION ENABLED" in [s for _, s in b.model.psm.history]
    with b.face.lock:
        assert abs(b.model.velocity_rad_s) < 0.05
    # an independent master reads the drive's objects alongside the guard
    assert b.app.sdo[0x6041].raw & 0x4F == 0x40  # SWITCH ON DISABLED
    assert abs(int(b.app.sdo[0x606C].raw)) < 50
    request(b.control, {"stop": True}, 30)
    b.thread.join(timeout=60)
    assert b.result == [0]
    final = b.status()
    assert final is not None
    books = final["nodes"][str(DRIVE)]
    granted = books["delivered_uj"] - books["returns_credited_uj"]
    drive = final["cia402"]["drives"][str(DRIVE)]
    # the proxy's books: everything granted was spent on what the meter saw
    assert drive["credited_uj"] == granted == drive["spent_uj"] + drive["usable_uj"]
    bound = overshoot_bound_uj(
        round(b.model.peak_power_w * 1e6),
        PDO_MS * 1000,
        drive["reaction_max_us"],
        stop_time_us(b.model),
    )
    assert b.drawn() <= granted + bound
    # the whole ledger: supervisor, the canergy node and the drive
    assert final["conservation"]["holds"] and final["usable_uj"] == 0
    node = b.node_host.nodes[NODE].client.state
    node_books = final["nodes"][str(NODE)]
    assert node.credited <= node_books["delivered_uj"]
    assert granted + node_books["delivered_uj"] == final["initial_uj"]
    # the proxy's leg was captured: the audit reads it
    assert (b.tmp / "proxy.log").stat().st_size > 0


def test_top_ups_keep_the_drive_running(plenty: Bench) -> None:
    b = plenty
    wait_for(lambda: b.model.state == "OPERATION ENABLED")
    time.sleep(3)  # ~9 W for 3 s: far more than one 1 J top-up
    drive = b.drive_status()
    assert drive is not None and drive["stops"] == 0 and drive["guard"] == "running"
    assert b.model.state == "OPERATION ENABLED"
    history = [s for _, s in b.model.psm.history]
    assert history[history.index("OPERATION ENABLED") :] == ["OPERATION ENABLED"]
    final = b.status()
    assert final is not None
    books = final["nodes"][str(DRIVE)]
    assert books["committed"] >= 3
    assert b.drawn() <= books["delivered_uj"] + 1_000_000  # a top-up's worth of slack at most
