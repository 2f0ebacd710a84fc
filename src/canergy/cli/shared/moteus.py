"""``canergy supervisor --moteus IDS``: flags and set-up of guarded moteus controllers (CAN FD)."""

from __future__ import annotations

import argparse
import secrets
import sys
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import can

from canergy.argtypes import add_duration, bounded_int, energy, node_ids
from canergy.cli.shared.cia402 import _number
from canergy.core import Timing
from canergy.devices.guard import REREAD_US, DeviceConfig, DeviceGuard
from canergy.devices.moteus import (
    BROADCAST,
    ID_MAX,
    PREFIX_MAX,
    MoteusLimits,
    MoteusMotor,
    MoteusProfile,
)
from canergy.live.devices.moteus_link import MoteusLink, MoteusLinkConfig

SAMPLED_WARNING = (
    "warning: --moteus-meter sampled integrates the controller's power register (0x007, where "
    "the firmware has it) between queries: guarantee none, no bound; use envelope metering for "
    "a guarantee (docs/guide/drives.md: moteus controllers)"
)
UNREADABLE = (
    "the moteus limits did not read back (no answer to conf get on diagnostic channel 1 within "
    "the time allowed)"
)


def add_moteus_flags(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group(
        "moteus controllers",
        "guard moteus controllers over CAN FD (give --fd): each gets a proxy client, its power, "
        "current and velocity limits and its watchdog are written to its configuration (conf "
        "set on diagnostic channel 1) and read back (conf get), the power they allow is charged "
        "by the clock, and mode 0 (stopped) stops it when its budget runs out; a controller "
        "that does not stop is reported STUCK",
    )
    g.add_argument("--moteus", type=node_ids, metavar="IDS", help="controller ids 1-127, e.g. 1,2")
    g.add_argument(
        "--moteus-meter",
        choices=("envelope", "sampled"),
        default="envelope",
        help="envelope: the limits' power by the clock, sound; sampled: the power register "
        "0x007, no guarantee (default envelope)",
    )
    g.add_argument(
        "--moteus-max-power",
        type=_number("W", 100_000, zero=False),
        metavar="WATTS",
        help="servo.max_power_W the guard writes (envelope metering)",
    )
    g.add_argument(
        "--moteus-max-current",
        type=_number("A", 1000, zero=False),
        metavar="AMPS",
        help="servo.max_current_A the guard writes (envelope metering)",
    )
    g.add_argument(
        "--moteus-max-speed",
        type=_number("rev/s", 10_000, zero=False),
        metavar="REV_S",
        help="servo.max_velocity the guard writes, at the output (envelope metering)",
    )
    g.add_argument(
        "--moteus-torque-constant",
        type=_number("N·m/A", 100, zero=False),
        metavar="NM_PER_A",
        help="the motor's torque constant at the output",
    )
    g.add_argument(
        "--moteus-resistance",
        type=_number("ohms", 1000, zero=True),
        default=Fraction(0),
        metavar="OHMS",
        help="phase resistance (hot): copper losses 3/2·R·i² in the envelope (default 0)",
    )
    g.add_argument(
        "--moteus-velocity-derate",
        type=_number("rev/s", 10_000, zero=True),
        default=Fraction(2),
        metavar="REV_S",
        help="the controller's servo.max_velocity_derate: power reaches 0 only this far past "
        "the velocity limit (default 2)",
    )
    g.add_argument(
        "--moteus-bus-voltage",
        type=_number("V", 1000, zero=True),
        default=Fraction(0),
        metavar="VOLTS",
        help="the supply's highest voltage: the envelope is at most V_bus·i_max (raised to what "
        "register 0x00d shows; default 0: from the first reading)",
    )
    add_duration(
        g,
        "--moteus-watchdog",
        100_000,
        "servo.default_timeout_s the guard writes: the controller leaves position mode this "
        "long after the application's last command",
    )
    g.add_argument(
        "--moteus-source",
        type=bounded_int(0, ID_MAX),
        default=0x7E,
        metavar="ID",
        help="the guard's source id on the bus, its queries' answers come to it (default 126)",
    )
    g.add_argument(
        "--moteus-prefix",
        type=bounded_int(0, PREFIX_MAX),
        default=0,
        metavar="N",
        help="the controllers' can.prefix, the identifier's top 13 bits (default 0)",
    )
    g.add_argument(
        "--moteus-reserve",
        type=energy,
        default=0,
        metavar="ENERGY",
        help="kept on top of the bound; the whole margin with sampled metering (default 0)",
    )
    add_duration(g, "--moteus-feedback-timeout", 300_000, "stop a controller not heard this long")
    add_duration(
        g, "--moteus-reaction", 10_000, "host reaction the bound allows (raised to what is seen)"
    )
    add_duration(
        g,
        "--moteus-latency",
        5_000,
        "controller latency the bound allows (raised to what is seen)",
    )
    add_duration(
        g,
        "--moteus-stop-timeout",
        500_000,
        "a controller not stopped this long after a stop is STUCK",
    )


def check_moteus(args: argparse.Namespace) -> None:
    """Everything about the controllers that can be judged before the bus is opened."""
    ids = args.moteus or ()
    if not ids:
        return
    others = [f for f, on in (("--cia402", args.cia402), ("--odrive", args.odrive)) if on]
    if others or args.canopen:
        raise ValueError(
            f"--moteus and {' and '.join(others) or '--canopen'} on one bus: a moteus command "
            "from source 0 to id 3 is the standard frame 0x003, which CANopen and CAN Simple "
            "read as their own; guard them on two buses"
        )
    if set(ids) & set(args.nodes or ()):
        raise ValueError("a node id is either a canergy node (--nodes) or a moteus (--moteus)")
    if args.moteus_source in ids:
        raise ValueError(f"--moteus-source {args.moteus_source} is also a controller id")
    if args.moteus_source == BROADCAST:
        raise ValueError(
            f"--moteus-source {BROADCAST} is the broadcast id: every controller takes a frame to "
            "it as its own, so the answers to the guard's queries would read as commands"
        )
    if args.id_base >> 16 == args.moteus_prefix:
        raise ValueError(
            f"--moteus-prefix {args.moteus_prefix}: its identifiers are canergy's "
            f"(--id-base 0x{args.id_base:08X})"
        )
    if args.listen_only:
        raise ValueError("--moteus guards controllers and must send: not with --listen-only")
    if not getattr(args, "fd", False):  # python-can's flag: absent unless given
        raise ValueError("--moteus: moteus speaks CAN FD: give --fd (and --data-bitrate)")
    if args.moteus_meter == "sampled":
        print(SAMPLED_WARNING, file=sys.stderr)
        return
    flags = (
        "--moteus-max-power",
        "--moteus-max-current",
        "--moteus-max-speed",
        "--moteus-torque-constant",
    )
    missing = [f for f in flags if getattr(args, f[2:].replace("-", "_")) is None]
    if missing:
        raise ValueError(f"--moteus-meter envelope needs {', '.join(missing)}")


def moteus_limits(args: argparse.Namespace) -> MoteusLimits:
    return MoteusLimits(
        float(args.moteus_max_power or 0),
        float(args.moteus_max_current or 0),
        float(args.moteus_max_speed or 0),
        args.moteus_watchdog / 1e6,
    ).wire()


@dataclass(frozen=True, slots=True)
class MoteusControllers:
    """``--moteus``: the controllers and their guards' and links' configuration
    (``canergy.live.supervisor.build.DeviceGroup``)."""

    nodes: tuple[int, ...]
    guard: DeviceConfig[MoteusLimits]
    link: MoteusLinkConfig
    motor: MoteusMotor

    def open(
        self, bus: can.BusABC, now: int, clock: Any, wake: Any = None
    ) -> dict[int, tuple[DeviceGuard[MoteusLimits], MoteusLink]]:
        """A guard and a link per controller (the links' listeners still to be added)."""
        limits = None if self.guard.sampled else self.guard.limits
        devices = {}
        for n in self.nodes:
            guard = DeviceGuard(n, MoteusProfile(self.motor), self.guard, now, secrets.randbits(16))
            devices[n] = (guard, MoteusLink(bus, n, self.link, limits, clock))
        return devices


def moteus_controllers(args: argparse.Namespace, timing: Timing) -> MoteusControllers:
    """The ``--moteus*`` flags as the builder takes them."""
    sampled = args.moteus_meter == "sampled"
    config = DeviceConfig(
        limits=moteus_limits(args),
        sampled=sampled,
        timing=timing,
        reaction_us=args.moteus_reaction,
        latency_us=args.moteus_latency,
        feedback_timeout_us=args.moteus_feedback_timeout,
        stop_timeout_us=args.moteus_stop_timeout,
        reserve_uj=args.moteus_reserve,
        reread_us=REREAD_US,
        unreadable=UNREADABLE,
    )
    link = MoteusLinkConfig(source=args.moteus_source, prefix=args.moteus_prefix, sampled=sampled)
    motor = MoteusMotor(
        torque_constant=args.moteus_torque_constant or Fraction(0),
        resistance=args.moteus_resistance,
        velocity_derate=args.moteus_velocity_derate,
        bus_voltage=args.moteus_bus_voltage,
    )
    return MoteusControllers(tuple(args.moteus), config, link, motor)


def moteus_filters(args: argparse.Namespace) -> list[dict[str, int | bool]]:
    """Acceptance filters for the controllers' frames: extended ones of their prefix (standard
    ones pass with CANopen's filter)."""
    return [{"can_id": args.moteus_prefix << 16, "can_mask": PREFIX_MAX << 16, "extended": True}]
