"""A guarded drive on python-can's virtual bus, on the wall clock: ``canergy supervisor --cia402``
(its real ``main``, in a thread) against the emulated drive (``DriveFace``), a canergy node, and a
python-canopen application that sets profile velocity and a target velocity.

``guarded_bench(...)`` is the test bench; ``python -m firmware_model.drive.live_bench`` measures
the overshoot past a 2 J budget for several TPDO periods, with the reaction and stop times of the
same run in the bound.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import canopen

from canergy.cia402.meter import overshoot_bound_uj
from canergy.cli import main as canergy_main
from canergy.codec import Codec
from canergy.live.cia402_link import EDS
from canergy.live.control import request
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.messages import Direction
from firmware_model.actuator import PowerProfile
from firmware_model.drive.canopen_face import DriveFace, drive_network
from firmware_model.drive.model import EDS as DRIVE_EDS
from firmware_model.drive.model import DriveModel
from firmware_model.drive.motor import LoadTorque
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore

DRIVE, NODE = 10, 1


def wait_for(condition: Callable[[], Any], timeout: float = 60.0) -> Any:
    """Poll until ``condition()`` is truthy and return it; AssertionError after ``timeout``."""
    end = time.monotonic() + timeout
    while not (value := condition()):
        if time.monotonic() > end:
            raise AssertionError("timed out")
        time.sleep(0.02)
    return value


@dataclass
class Bench:
    tmp: Path
    pdo_ms: int
    model: DriveModel
    face: DriveFace
    app: canopen.RemoteNode
    control: Path
    result: list[int]
    thread: threading.Thread
    node_host: NodeHost

    def status(self) -> dict[str, Any] | None:
        try:
            return dict(json.loads((self.tmp / "status.json").read_text()))
        except (FileNotFoundError, json.JSONDecodeError):
            return None

    def drive_status(self) -> dict[str, Any] | None:
        status = self.status()
        return None if status is None else dict(status["cia402"]["drives"][str(DRIVE)])

    def drawn(self) -> int:
        with self.face.lock:
            return self.model.drawn_uj

    def stop(self) -> dict[str, Any]:
        """Stop the supervisor; its final status."""
        request(self.control, {"stop": True}, 30)
        self.thread.join(timeout=60)
        final = self.status()
        assert final is not None and self.result == [0]
        return final

    def stop_time_us(self) -> int:
        """From quick stop to the drive's power stage off, from its own history."""
        with self.face.lock:
            history = list(self.model.psm.history)
        start = next(t for t, s in history if s == "QUICK STOP ACTIVE")
        return next(t for t, s in history if t > start and s != "QUICK STOP ACTIVE") - start

    def bound_uj(self, reaction_us: int) -> int:
        return overshoot_bound_uj(
            round(self.model.peak_power_w * 1e6),
            self.pdo_ms * 1000,
            reaction_us,
            self.stop_time_us(),
        )


@contextlib.contextmanager
def guarded_bench(
    tmp: Path, pdo_ms: int, *supervisor_args: str, with_node: bool = True
) -> Iterator[Bench]:
    """The drive (its TPDOs every ``pdo_ms``), the supervisor guarding it with the drive's own EDS
    (as a bench user gives the vendor's), and with ``with_node`` a canergy node (0.2 W) beside."""
    channel = f"cia402-{uuid.uuid4().hex}"
    now = monotonic_us()
    model = DriveModel(
        DRIVE,
        now,
        load=LoadTorque.constant(0.02, opposing=True),
        defaults={(0x1800 + i, 5): pdo_ms for i in range(3)},
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
    node_host = NodeHost([node] if with_node else [])
    node_bus = can.Bus(interface="virtual", channel=channel)
    node_runtime = BusRuntime(node_bus, node_host, codec=Codec(), receives=Direction.TO_CLIENT)
    node_stop = threading.Event()
    node_thread = threading.Thread(
        target=node_runtime.run, args=(node_stop.is_set, 0.02), daemon=True
    )
    node_thread.start()
    app_bus = can.Bus(interface="virtual", channel=channel)
    app_net = canopen.Network(app_bus)
    app_net.notifier = can.Notifier(app_bus, list(app_net.listeners), 0.1)
    app = canopen.RemoteNode(DRIVE, str(EDS))
    app.sdo.RESPONSE_TIMEOUT = 2.0
    app_net.add_node(app)
    control = tmp / "ctl.sock"
    argv = [
        "supervisor",
        *("-i", "virtual", "-c", channel),
        *(("--nodes", str(NODE)) if with_node else ()),
        *("--cia402", str(DRIVE), "--cia402-eds", str(DRIVE_EDS)),
        *("--state", str(tmp / "s.json"), "--no-fsync"),
        *("--status-file", str(tmp / "status.json"), "--status-period", "50ms"),
        *("--control", str(control)),
        *("--max-grant", "500mJ", "--response-timeout", "100ms"),
        *("--cia402-resistance", "1", "--cia402-enable"),
        *("--cia402-capture", str(tmp / "proxy.log")),
        *supervisor_args,
    ]
    result: list[int] = []
    thread = threading.Thread(target=lambda: result.append(canergy_main(argv)), daemon=True)
    thread.start()
    bench = Bench(tmp, pdo_ms, model, face, app, control, result, thread, node_host)
    try:
        wait_for(lambda: (d := bench.drive_status()) and d["ready"])
        app.sdo[0x6060].raw = 3  # profile velocity
        app.sdo[0x6083].raw = 1_000_000  # 1000 rad/s²
        app.sdo[0x60FF].raw = 100_000  # 100 rad/s
        yield bench
    finally:
        if thread.is_alive() and control.exists():
            request(control, {"stop": True}, 30)
        thread.join(timeout=60)
        node_stop.set()
        node_thread.join(timeout=30)
        node_bus.shutdown()
        face.close()
        for net in (drive_net, app_net):
            if net.notifier is not None:
                net.notifier.stop()
            if net.bus is not None:
                net.bus.shutdown()


def exhausted(bench: Bench) -> dict[str, Any] | None:
    """The guard's status once it has stopped the drive for an exhausted budget."""
    d = bench.drive_status()
    done = (
        d is not None
        and d["stop_reason"] == "budget exhausted"
        and d["guard"] == "stopped"
        and d["drive_state"] == "SWITCH ON DISABLED"
    )
    return d if done else None


def measure(pdo_ms: int) -> dict[str, Any]:
    with (
        tempfile.TemporaryDirectory() as tmp,
        guarded_bench(
            Path(tmp), pdo_ms, "--initial", "2J", "--target", "1J", with_node=False
        ) as bench,
    ):
        wait_for(lambda: exhausted(bench), timeout=120)
        final = bench.stop()
        books = final["nodes"][str(DRIVE)]
        drive = final["cia402"]["drives"][str(DRIVE)]
        granted = books["delivered_uj"] - books["returns_credited_uj"]
        return {
            "pdo_ms": pdo_ms,
            "granted_uj": granted,
            "drawn_uj": bench.drawn(),
            "reaction_us": drive["reaction_max_us"],
            "stop_us": bench.stop_time_us(),
            "peak_power_w": bench.model.peak_power_w,
            "bound_uj": bench.bound_uj(drive["reaction_max_us"]),
        }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pdo-ms", type=int, nargs="+", default=[5, 10, 20, 50])
    args = parser.parse_args()
    print("| TPDO period | granted | drawn | overshoot | host reaction | stop time | bound |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for ms in args.pdo_ms:
        r = measure(ms)
        over = max(0, r["drawn_uj"] - r["granted_uj"])
        print(
            f"| {ms} ms | {r['granted_uj'] / 1e6:.3f} J | {r['drawn_uj'] / 1e6:.4f} J | "
            f"{over / 1e3:.1f} mJ | {r['reaction_us'] / 1e3:.1f} ms | {r['stop_us'] / 1e3:.1f} ms"
            f" | {r['bound_uj'] / 1e3:.0f} mJ |"
        )


if __name__ == "__main__":
    main()
