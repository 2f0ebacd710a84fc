"""``canergy supervisor --cia402 IDS``: flags and set-up of guarded CiA 402 drives."""

from __future__ import annotations

import argparse
import math
import secrets
import sys
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import can

from canergy.argtypes import (
    add_duration,
    bounded_int,
    duration,
    duration_or_zero,
    energy,
    node_ids,
)
from canergy.cia402.counter import CounterConfig
from canergy.cia402.envelope import Limits, StopKind
from canergy.cia402.guard import DriveGuard, GuardConfig
from canergy.cia402.meter import MeterConfig, MeterKind
from canergy.core import Timing
from canergy.live.canopen.cia402_host import HostBeat
from canergy.live.canopen.cia402_link import EDS, DriveLink, LinkConfig

CONSUMER_MAX_US = 65_535_000  # 0x1016 holds milliseconds in 16 bits


def _number(what: str, high: float, *, zero: bool) -> Any:
    """A decimal number of ``what`` (exact, as a fraction), up to ``high``; 0 only if ``zero``."""

    def parse(text: str) -> Fraction:
        try:
            value = Fraction(text.strip())
        except (ValueError, ZeroDivisionError):
            raise argparse.ArgumentTypeError(f"not a number of {what}: {text[:40]!r}") from None
        low = "0" if zero else "more than 0"
        if value > high or value < 0 or (value == 0 and not zero):
            raise argparse.ArgumentTypeError(
                f"{text[:40]}: must be {low} and at most {high} {what}"
            )
        return value

    return parse


RENAMED = {"mechanical": "sampled-mechanical", "electrical": "sampled-electrical"}
SAMPLED_WARNING = (
    "warning: --cia402-meter {mode} samples power at TPDO instants only: motion timed between "
    "two TPDOs is not metered and no bound is claimed; use counter or envelope metering for a "
    "guarantee (docs/guide/drives.md: Guarding CiA 402 drives)"
)


def meter_name(text: str) -> str:
    """A metering mode's name (argparse checks the choices); the old names of the sampled
    modes say what they became."""
    if text in RENAMED:
        raise argparse.ArgumentTypeError(
            f"{text!r} is now {RENAMED[text]!r}: it samples power and can be fooled; "
            "counter or envelope metering is sound"
        )
    if text not in {k.value for k in MeterKind}:
        modes = ", ".join(k.value for k in MeterKind)
        raise argparse.ArgumentTypeError(f"{text[:40]!r}: one of {modes}")
    return text


def counter_object(text: str) -> tuple[int | None, int, int]:
    """``[NODE:]INDEX[.SUB]``, e.g. ``0x2011`` (on the drive) or ``20:0x2100`` (node 20)."""
    node_text, _, obj = text.strip().rpartition(":")
    index_text, _, sub_text = obj.partition(".")
    try:
        node = int(node_text, 0) if node_text else None
        index, sub = int(index_text, 16), int(sub_text or "0", 0)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text[:40]!r}: [NODE:]INDEX[.SUB], e.g. 0x2011 or 20:0x2100"
        ) from None
    if node is not None and not 1 <= node <= 127:
        raise argparse.ArgumentTypeError(f"{text[:40]!r}: node id 1-127")
    if not 0x1000 <= index <= 0xFFFF or not 0 <= sub <= 0xFF:
        raise argparse.ArgumentTypeError(f"{text[:40]!r}: index 0x1000-0xFFFF, sub-index 0-255")
    return node, index, sub


def counter_bits(text: str) -> int:
    """8, 16, 32 or 64."""
    if text.strip() not in ("8", "16", "32", "64"):
        raise argparse.ArgumentTypeError(f"{text[:24]!r}: 8, 16, 32 or 64 bits")
    return int(text)


def add_cia402_flags(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group(
        "CiA 402 drives",
        "guard off-the-shelf CANopen drives: each gets a proxy client in the supervisor's books, "
        "is metered from its TPDOs, and is quick-stopped and disabled when its budget runs out "
        "or its TPDOs stop; the drives consume the host's heartbeat (0x1016) and fault when it "
        "stops",
    )
    g.add_argument("--cia402", type=node_ids, metavar="IDS", help="drive node ids, e.g. 10-12")
    g.add_argument("--cia402-eds", type=Path, help=f"the drives' EDS (default: {EDS.name})")
    g.add_argument(
        "--cia402-meter",
        type=meter_name,
        choices=[k.value for k in MeterKind],
        help="counter: a cumulative energy object (--cia402-counter), sound and tight; "
        "envelope: the limits the guard writes (--cia402-max-*), charged at their largest "
        "power by the clock, sound; sampled-mechanical / sampled-electrical: power at TPDO "
        "instants, no guarantee (required with --cia402)",
    )
    g.add_argument(
        "--cia402-counter",
        type=counter_object,
        metavar="[NODE:]INDEX[.SUB]",
        help="counter metering: the energy object, on the drive (0x2011) or on a power-meter "
        "node (20:0x2100); its TPDO must carry it",
    )
    g.add_argument(
        "--cia402-counter-unit",
        type=energy,
        default=1,
        metavar="ENERGY",
        help="what one count is (default 1uJ; e.g. 1mJ, 0.36J for 0.1 mWh)",
    )
    g.add_argument(
        "--cia402-counter-bits",
        type=counter_bits,
        choices=(8, 16, 32, 64),
        default=32,
        help="the counter's width: it wraps at 2**bits counts (default 32)",
    )
    for flag, index, high, unit, metavar in (
        ("--cia402-max-torque", 0x6072, 65535, "‰ of rated torque", "PERMILLE"),
        ("--cia402-max-current", 0x6073, 65535, "‰ of rated current", "PERMILLE"),
        ("--cia402-max-speed", 0x6080, 2**32 - 1, "in the drive's velocity unit", "UNITS"),
    ):
        g.add_argument(
            flag,
            type=bounded_int(1, high),
            metavar=metavar,
            help=f"0x{index:04X} the guard writes, {unit} (counter and envelope metering)",
        )
    for flag, index, high in (
        ("--cia402-reach-torque", 0x6072, 65535),
        ("--cia402-reach-current", 0x6073, 65535),
        ("--cia402-reach-speed", 0x6080, 2**32 - 1),
    ):
        g.add_argument(
            flag,
            type=bounded_int(1, high),
            metavar="VALUE",
            help=f"the most 0x{index:04X} can be set to on the drive: a write the guard has not "
            "verified yet is charged at it (default: the EDS's HighLimit, else the type's range)",
        )
    g.add_argument(
        "--cia402-reread",
        type=duration_or_zero,
        default=1_000_000,
        metavar="TIME",
        help="read the drive's configuration back this often, for writes the guard cannot see "
        "(default 1s; 0: never)",
    )
    g.add_argument(
        "--cia402-stop",
        choices=[k.value for k in StopKind],
        default=StopKind.QUICK.value,
        help="quick: quick stop, then disable voltage once standing (the bound adds what the "
        "stop can draw); disable: disable voltage at once, the drive coasts (default quick)",
    )
    g.add_argument(
        "--cia402-bus-current",
        type=bounded_int(0x2000, 0x5FFF),
        metavar="INDEX",
        help="electrical metering: the object holding the DC link current in mA, e.g. 0x2010",
    )
    g.add_argument(
        "--cia402-resistance",
        type=_number("ohms", 1000, zero=True),
        default=Fraction(0),
        metavar="OHMS",
        help="winding resistance (hot): copper losses in the envelope and in sampled-mechanical "
        "metering (default 0)",
    )
    g.add_argument(
        "--cia402-velocity-unit",
        type=_number("rad/s", 1000, zero=False),
        default=Fraction(1, 1000),
        metavar="RAD_S",
        help="what one unit of 0x606C is in rad/s (default 0.001; rpm: 0.10471975512)",
    )
    g.add_argument(
        "--cia402-credit-regen",
        action="store_true",
        help="let power flowing back offset energy drawn later (default: not credited)",
    )
    g.add_argument(
        "--cia402-reserve",
        type=energy,
        default=0,
        help="keep this on top of the bound (sound modes; a drive whose bound exceeds a reserve "
        "given here is refused) or as the whole margin (sampled modes) (default 0)",
    )
    g.add_argument(
        "--cia402-enable",
        action="store_true",
        help="bring a drive to OPERATION ENABLED while it holds budget (default: the "
        "application enables it; the guard only stops it)",
    )
    add_duration(
        g, "--cia402-pdo-timeout", 200_000, "stop when TPDOs stop this long: the bound's gap"
    )
    add_duration(
        g, "--cia402-reaction", 10_000, "host reaction the bound allows (raised to what is seen)"
    )
    add_duration(
        g, "--cia402-latency", 5_000, "drive latency the bound allows (raised to what is seen)"
    )
    add_duration(g, "--cia402-stop-timeout", 1_000_000, "disable this long after quick stop")
    add_duration(g, "--cia402-heartbeat", 100_000, "host heartbeat period")
    add_duration(
        g,
        "--cia402-consumer-timeout",
        500_000,
        "written to each drive's 0x1016:1: it faults after this long without the host",
    )
    g.add_argument("--cia402-sync", type=duration, metavar="TIME", help="send SYNC this often")
    g.add_argument("--cia402-host-id", type=bounded_int(1, 127), default=127)
    g.add_argument(
        "--cia402-capture",
        type=Path,
        metavar="FILE",
        help="log the proxies' canergy frames (any python-can format: .log, .asc, .blf, .csv) "
        "for `canergy audit`",
    )


def check_cia402(args: argparse.Namespace) -> None:
    """Everything about the drives that can be judged before the bus is opened."""
    drives = args.cia402 or ()
    nodes = args.nodes or ()
    devices = any(getattr(args, flag, None) for flag in ("odrive", "moteus", "mit"))
    if not drives and not nodes and not devices:
        raise ValueError("give --nodes, --cia402 or both (or --bus for several buses)")
    if not drives:
        return
    if set(drives) & set(nodes):
        raise ValueError("a node id is either a canergy node (--nodes) or a drive (--cia402)")
    if args.cia402_host_id in (*drives, *nodes):
        raise ValueError(f"--cia402-host-id {args.cia402_host_id} is also a node or drive id")
    if args.cia402_meter is None:
        modes = ", ".join(k.value for k in MeterKind)
        raise ValueError(f"--cia402 needs --cia402-meter MODE ({modes}): see docs/guide/drives.md")
    kind = MeterKind(args.cia402_meter)
    if kind is MeterKind.SAMPLED_ELECTRICAL and args.cia402_bus_current is None:
        raise ValueError("--cia402-meter sampled-electrical needs --cia402-bus-current INDEX")
    if not kind.sampled:
        flags = ("--cia402-max-torque", "--cia402-max-current", "--cia402-max-speed")
        missing = [f for f in flags if getattr(args, f[2:].replace("-", "_")) is None]
        if missing:
            raise ValueError(f"--cia402-meter {kind.value} needs {', '.join(missing)}")
    for what in ("torque", "current", "speed"):
        limit, reach = (getattr(args, f"cia402_{k}_{what}") for k in ("max", "reach"))
        if limit is not None and reach is not None and reach < limit:
            raise ValueError(f"--cia402-reach-{what} {reach} is below --cia402-max-{what}")
    if kind is MeterKind.COUNTER:
        if args.cia402_counter is None:
            raise ValueError("--cia402-meter counter needs --cia402-counter [NODE:]INDEX")
        meter_node = args.cia402_counter[0]
        if meter_node is not None and len(drives) > 1:
            raise ValueError("a power-meter node meters one drive: give one --cia402 id")
        if meter_node in (*drives, *nodes, args.cia402_host_id):
            raise ValueError(f"--cia402-counter node {meter_node} is also a node or drive id")
    if args.cia402_counter_unit < 1:
        raise ValueError("--cia402-counter-unit: at least 1uJ")
    if args.cia402_consumer_timeout > CONSUMER_MAX_US or args.cia402_consumer_timeout % 1000:
        raise ValueError("--cia402-consumer-timeout: whole milliseconds, at most 65535ms")
    if args.cia402_consumer_timeout < 2 * args.cia402_heartbeat:
        raise ValueError(
            "--cia402-consumer-timeout must be at least twice --cia402-heartbeat, or one late "
            "heartbeat faults the drives"
        )
    if args.listen_only:
        raise ValueError("--cia402 guards drives and must send: not with --listen-only")
    if kind.sampled:
        print(SAMPLED_WARNING.format(mode=kind.value), file=sys.stderr)
    import canopen

    try:
        canopen.import_od(str(args.cia402_eds or EDS))
    except Exception as exc:  # canopen raises what its parsers raise
        raise ValueError(f"--cia402-eds {args.cia402_eds}: not a usable EDS ({exc})") from None


@dataclass(frozen=True, slots=True)
class Cia402Drives:
    """``--cia402``: the drives, their guards' and links' configuration, the host's heartbeat,
    the capture file (``canergy.live.supervisor.build.Cia402Group``)."""

    nodes: tuple[int, ...]
    guard: GuardConfig
    link: LinkConfig
    beat: HostBeat
    capture: Path | None

    def open(
        self, network: Any, now: int, clock: Any
    ) -> tuple[dict[int, tuple[Any, Any]], HostBeat, can.Listener | None]:
        # the capture first: a file that cannot be opened leaves no link thread behind
        capture = can.Logger(str(self.capture)) if self.capture else None
        drives: dict[int, tuple[Any, Any]] = {
            n: (
                DriveGuard(n, self.guard, now, secrets.randbits(16)),
                DriveLink(network, n, self.link, clock),
            )
            for n in self.nodes
        }
        return drives, self.beat, capture


def cia402_drives(args: argparse.Namespace, timing: Timing) -> Cia402Drives:
    """The ``--cia402*`` flags as the builder takes them."""
    kind = MeterKind(args.cia402_meter)
    meter = MeterConfig(
        kind=kind,
        velocity_unit_rad_s=args.cia402_velocity_unit,
        resistance_mohm=math.ceil(args.cia402_resistance * 1000),
        bus_current_index=args.cia402_bus_current,
        credit_regen=args.cia402_credit_regen,
    )
    limits = None
    if not kind.sampled:
        limits = Limits(args.cia402_max_torque, args.cia402_max_current, args.cia402_max_speed)
    counter = None
    if kind is MeterKind.COUNTER:
        node, index, sub = args.cia402_counter
        counter = CounterConfig(
            index, sub, node, args.cia402_counter_bits, args.cia402_counter_unit
        )
    stop = StopKind(args.cia402_stop)
    config = GuardConfig(
        meter=meter,
        limits=limits,
        counter=counter,
        stop=stop,
        timing=timing,
        pdo_timeout_us=args.cia402_pdo_timeout,
        stop_timeout_us=args.cia402_stop_timeout,
        reaction_us=args.cia402_reaction,
        latency_us=args.cia402_latency,
        reserve_uj=args.cia402_reserve,
        auto_enable=args.cia402_enable,
        reread_us=args.cia402_reread,
    )
    link_config = LinkConfig(
        eds=args.cia402_eds or EDS,
        meter=meter,
        limits=limits,
        counter=counter,
        stop=stop,
        host_id=args.cia402_host_id,
        consumer_timeout_ms=args.cia402_consumer_timeout // 1000,
        reach=(args.cia402_reach_torque, args.cia402_reach_current, args.cia402_reach_speed),
    )
    beat = HostBeat(args.cia402_host_id, args.cia402_heartbeat, args.cia402_sync)
    return Cia402Drives(tuple(args.cia402), config, link_config, beat, args.cia402_capture or None)
