"""A guarded drive on python-can's virtual bus, on the wall clock: ``canergy supervisor --cia402``
(its real ``main``, in a thread) against the emulated drive (``DriveFace``), a canergy node, and a
python-canopen application that sets profile velocity and a target velocity.

``guarded_bench(...)`` is the test bench; ``python -m firmware_model.drive.live_bench`` measures
what the drive drew against a 2 J grant for several TPDO periods and metering modes, beside the
bound the guard showed (its reaction and latency as measured in the same run).
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
from typing import Any, TypeVar

import can
import canopen

from canergy.cli import main as canergy_main
from canergy.codec import Codec
from canergy.live.canopen.cia402_link import EDS, shared_sdo
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.live.supervisor.control import request
from canergy.messages import Direction
from firmware_model.actuator import PowerProfile
from firmware_model.drive.canopen_face import DriveFace, drive_network
from firmware_model.drive.model import EDS as DRIVE_EDS
from firmware_model.drive.model import DriveModel
from firmware_model.drive.motor import LoadTorque
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore

DRIVE, NODE = 10, 1
T = TypeVar("T")
LIMITS = ("--cia402-max-torque", "265", "--cia402-max-current", "265")
"""With ``--cia402-max-speed 100500``: the 15 W envelope of ``cosim.FIFTEEN_WATTS``."""


def metering(mode: str, pdo_ms: int, gap_ms: int | None = None) -> tuple[str, ...]:
    """The guard's flags for ``mode`` (``counter``, ``envelope`` or a sampled one): the 15 W
    limits, a coasting stop and a PDO timeout of ``gap_ms`` (default ten periods and at least
    100 ms: threads on a loaded machine jitter, and a late TPDO must not latch a stop)."""
    flags: tuple[str, ...] = ("--cia402-meter", mode, "--cia402-resistance", "1")
    if mode == "counter":
        flags += ("--cia402-counter", "0x2011")
    if mode in ("counter", "envelope"):
        flags += (*LIMITS, "--cia402-max-speed", "100500", "--cia402-stop", "disable")
        flags += ("--cia402-pdo-timeout", f"{gap_ms or max(10 * pdo_ms, 100)}ms")
    return flags


def wait_for(
    condition: Callable[[], Any], timeout: float = 60.0, show: Callable[[], Any] | None = None
) -> Any:
    """Poll until ``condition()`` is truthy and return it; AssertionError after ``timeout``
    (saying what ``show()`` returns then, if given)."""
    end = time.monotonic() + timeout
    while not (value := condition()):
        if time.monotonic() > end:
            raise AssertionError("timed out" if show is None else f"timed out: {show()}")
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


APP_SDO_PATIENCE_S = 10.0
"""How long the application's SDO write keeps trying past the guard's transfers."""


def app_write(node: canopen.RemoteNode, index: int, value: int) -> None:
    """An application's SDO write, beside the guard's on the drive's one SDO server."""

    def transfer() -> None:
        node.sdo[index].raw = value

    _patiently(transfer)


def app_read(node: canopen.RemoteNode, index: int) -> int:
    """An application's SDO read, beside the guard's on the drive's one SDO server."""
    return _patiently(lambda: int(node.sdo[index].raw))


def _patiently(transfer: Callable[[], T]) -> T:
    """The guard reads back too: once a second, and in bursts after each write it sees. On a
    loaded machine a burst can outlast ten tries; an application keeps trying, for a while."""
    deadline = time.monotonic() + APP_SDO_PATIENCE_S
    while True:
        try:
            return shared_sdo(transfer, time.sleep, attempts=10)
        except canopen.SdoCommunicationError:
            if time.monotonic() > deadline:
                raise


@contextlib.contextmanager
def guarded_bench(
    tmp: Path,
    pdo_ms: int,
    *supervisor_args: str,
    with_node: bool = True,
    mode: str = "counter",
    gap_ms: int | None = None,
) -> Iterator[Bench]:
    """The drive (its TPDOs every ``pdo_ms``), the supervisor guarding it with the drive's own EDS
    (as a bench user gives the vendor's) in metering ``mode`` (``metering``), and with
    ``with_node`` a canergy node (0.2 W) beside."""
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
    # the mode before the guard starts: a mode written while it guards is charged at the reach
    app_write(app, 0x6060, 3)  # profile velocity
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
        # the drive faults 2 s without the host's heartbeat, not 0.5 s: a loaded machine stalls
        # threads for 300-500 ms, and a faulted drive neither runs nor spends its budget
        *("--cia402-consumer-timeout", "2s"),
        *metering(mode, pdo_ms, gap_ms),
        "--cia402-enable",
        *("--cia402-capture", str(tmp / "proxy.log")),
        *supervisor_args,
    ]
    result: list[int] = []
    thread = threading.Thread(target=lambda: result.append(canergy_main(argv)), daemon=True)
    thread.start()
    bench = Bench(tmp, pdo_ms, model, face, app, control, result, thread, node_host)
    try:
        wait_for(lambda: (d := bench.drive_status()) and d["ready"])
        app_write(app, 0x6083, 1_000_000)  # 1000 rad/s²
        app_write(app, 0x60FF, 100_000)  # 100 rad/s
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


def measure(pdo_ms: int, mode: str) -> dict[str, Any]:
    """2 J for the drive alone, a PDO timeout of three periods (at least 40 ms)."""
    gap_ms = max(3 * pdo_ms, 40)
    with (
        tempfile.TemporaryDirectory() as tmp,
        guarded_bench(
            Path(tmp),
            pdo_ms,
            *("--initial", "2J", "--target", "2J"),
            with_node=False,
            mode=mode,
            gap_ms=gap_ms,
        ) as bench,
    ):
        wait_for(lambda: exhausted(bench), timeout=600)
        final = bench.stop()
        books = final["nodes"][str(DRIVE)]
        drive = final["cia402"]["drives"][str(DRIVE)]
        granted = books["delivered_uj"] - books["returns_credited_uj"]
        return {
            "pdo_ms": pdo_ms,
            "mode": mode,
            "granted_uj": granted,
            "drawn_uj": bench.drawn(),
            "reaction_us": drive["reaction_max_us"],
            "latency_us": drive["latency_max_us"],
            "gap_us": drive["worst_gap_us"],
            "bound_uj": drive["bound_uj"],
        }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pdo-ms", type=int, nargs="+", default=[5, 10, 20, 50])
    parser.add_argument("--modes", nargs="+", default=["counter", "envelope"])
    args = parser.parse_args()
    print(
        "| mode | TPDO period | granted | drawn | overshoot | worst gap | reaction | latency "
        "| bound |"
    )
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for mode in args.modes:
        for ms in args.pdo_ms:
            r = measure(ms, mode)
            over = max(0, r["drawn_uj"] - r["granted_uj"])
            print(
                f"| {mode} | {ms} ms | {r['granted_uj'] / 1e6:.3f} J | "
                f"{r['drawn_uj'] / 1e6:.4f} J | {over / 1e3:.1f} mJ | "
                f"{r['gap_us'] / 1e3:.1f} ms | "
                f"{r['reaction_us'] / 1e3:.1f} ms | {r['latency_us'] / 1e3:.1f} ms | "
                f"{r['bound_uj'] / 1e3:.0f} mJ |"
            )


if __name__ == "__main__":
    main()
