"""``python -m firmware_model.drive``: one emulated CiA 402 drive on any python-can bus.

The physics runs in real time (advanced every 1 ms of monotonic time). With ``--power-meter NODE``
a DC bus power meter node (``power_meter``) meters the drive on the same bus, its TPDO1 every
``--pdo-period``; the status gains its ``power_meter`` figures. Exit status: 0 after
SIGINT/SIGTERM (final status written), 2 for bad arguments or a bus that cannot be opened.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from canergy.argtypes import add_duration, bounded_int
from canergy.cli.shared.bus_flags import add_bus_flags, open_bus
from canergy.errors import BusOpenError
from canergy.live.atomic import check_writable_dir, same_file, write_json_atomic
from canergy.live.canopen.shared_bus import STANDARD_FRAMES
from canergy.live.runtime import monotonic_us
from firmware_model.drive.canopen_face import DriveFace, drive_network
from firmware_model.drive.model import DriveModel
from firmware_model.drive.motor import LoadTorque
from firmware_model.drive.power_meter import PowerMeterFace, PowerMeterModel


def newton_metres(text: str) -> float:
    """A torque in N·m, finite, at most 1000 in magnitude."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a torque in N·m: {text[:24]!r}") from None
    if not (math.isfinite(value) and abs(value) <= 1000):
        raise argparse.ArgumentTypeError(f"torque {text[:24]!r} outside -1000..1000 N·m")
    return value


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m firmware_model.drive",
        description="Emulate a CiA 402 servo drive (profiled velocity, cyclic synchronous "
        "torque) that accounts the electrical energy it draws.",
    )
    p.add_argument("--node", type=bounded_int(1, 127), required=True, help="node id")
    add_bus_flags(p, id_base_flag=False)  # a CiA 402 drive: no canergy frames
    load = p.add_mutually_exclusive_group()
    load.add_argument("--load-torque", type=newton_metres, default=0.0, help="N·m, constant")
    load.add_argument("--load-profile", type=Path, help="CSV of time_s,newton_metres rows")
    p.add_argument(
        "--load-opposes", action="store_true", help="the load opposes motion (like friction)"
    )
    add_duration(p, "--pdo-period", 10_000, "TPDO1-3 event timer, whole ms")
    add_duration(p, "--heartbeat-period", 100_000, "producer heartbeat time 0x1017, whole ms")
    p.add_argument(
        "--power-meter",
        type=bounded_int(1, 127),
        metavar="NODE",
        help="also emulate a DC bus power meter node metering this drive (0x2100 energy, mJ)",
    )
    p.add_argument("--status-file", type=Path, help="JSON status, rewritten atomically")
    add_duration(p, "--status-period", 1_000_000, "time between status file writes")
    return p


def _whole_ms(parser: argparse.ArgumentParser, flag: str, us: int) -> int:
    if us % 1000 or not 1 <= us // 1000 <= 0xFFFF:
        parser.error(f"{flag}: whole milliseconds from 1 ms to 65.535 s")
    return us // 1000


def _timers(
    parser: argparse.ArgumentParser, args: argparse.Namespace
) -> dict[tuple[int, int], int]:
    """Heartbeat period and TPDO event timers, as both nodes take them (errors: exit 2)."""
    pdo_ms = _whole_ms(parser, "--pdo-period", args.pdo_period)
    heartbeat_ms = _whole_ms(parser, "--heartbeat-period", args.heartbeat_period)
    return {(0x1017, 0): heartbeat_ms, **{(c, 5): pdo_ms for c in (0x1800, 0x1801, 0x1802)}}


def _model(
    parser: argparse.ArgumentParser, args: argparse.Namespace, timers: dict[tuple[int, int], int]
) -> DriveModel:
    """The drive as the options describe it (errors: exit 2)."""
    if args.power_meter == args.node:
        parser.error("--power-meter: another node id than --node")
    try:
        if args.status_file is not None:
            check_writable_dir(args.status_file, "--status-file")
        if args.load_profile is not None:
            if args.status_file is not None and same_file(args.load_profile, args.status_file):
                raise ValueError("--load-profile and --status-file name the same file")
            load = LoadTorque.from_csv(args.load_profile, args.load_opposes)
        else:
            load = LoadTorque.constant(args.load_torque, args.load_opposes)
    except (ValueError, OSError) as exc:
        parser.exit(2, f"{parser.prog}: error: {exc}\n")
    return DriveModel(args.node, monotonic_us(), load=load, defaults=timers)


def _meter(node: int, face: DriveFace, timers: dict[tuple[int, int], int]) -> PowerMeterFace:
    """Power meter ``node`` on the drive's network, reading the drive's energy drawn when asked."""

    def drawn_uj() -> int:
        with face.lock:
            face.model.advance(face.clock())
            return face.model.drawn_uj

    def dc_voltage_mv() -> int:
        with face.lock:
            return face.model.read(0x6079)

    model = PowerMeterModel(
        node,
        drawn_uj,
        monotonic_us(),
        voltage_mv=dc_voltage_mv,
        defaults={key: timers[key] for key in ((0x1017, 0), (0x1800, 5))},
    )
    return PowerMeterFace(model, face.network)


class _Signals:
    """SIGINT and SIGTERM ask for a clean stop."""

    def __init__(self) -> None:
        self.stop = False
        signal.signal(signal.SIGINT, self._request_stop)
        signal.signal(signal.SIGTERM, self._request_stop)

    def _request_stop(self, signum: int, frame: object) -> None:
        self.stop = True


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    signals = _Signals()
    timers = _timers(parser, args)
    model = _model(parser, args, timers)
    try:
        bus = open_bus(args, [STANDARD_FRAMES])
    except BusOpenError as exc:
        parser.exit(2, f"{parser.prog}: error: {exc}\n")
    network = drive_network(bus)
    face = DriveFace(model, network)
    meter = None if args.power_meter is None else _meter(args.power_meter, face, timers)
    next_status = 0

    def status() -> dict[str, Any]:
        if meter is None:
            return face.status()
        # the meter advances the drive as it reads it: both figures of one instant. The locks
        # in the order the meter's own reads take them (its, then the drive's), or the two
        # would deadlock on each other
        with meter.lock, face.lock:
            metered = meter.status()
            return {**face.status(advance=False), "power_meter": metered}

    def every(now: int) -> None:
        nonlocal next_status
        if args.status_file is not None and now >= next_status:
            write_json_atomic(args.status_file, status(), fsync=False)
            next_status = now + args.status_period

    try:
        face.boot()
        if meter is not None:
            meter.boot()
            meter.start()
        face.run(lambda: signals.stop, every)
    finally:
        if meter is not None:
            meter.close()
        face.close()
        if network.notifier is not None:
            network.notifier.stop()
        bus.shutdown()
    final = status()
    if args.status_file is not None:
        write_json_atomic(args.status_file, final, fsync=False)
    else:
        print(json.dumps(final, sort_keys=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
