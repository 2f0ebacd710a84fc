"""``canergy supervisor --odrive IDS``: flags and set-up of guarded ODrive axes (CAN Simple)."""

from __future__ import annotations

import argparse
import secrets
import sys
from collections.abc import Callable
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import can

from canergy.argtypes import add_duration, energy, node_ids
from canergy.cli.shared.cia402 import _number
from canergy.core import Timing
from canergy.devices.guard import REREAD_US, DeviceConfig, DeviceGuard
from canergy.devices.odrive import FIRMWARES, NODE_MAX, MotorConstants, OdriveLimits, OdriveProfile
from canergy.devices.watchdog import WatchdogPolicy
from canergy.live.devices.odrive_link import OdriveLink, OdriveLinkConfig

SAMPLED_WARNING = (
    "warning: --odrive-meter sampled integrates the axis's power readings (0x01D on 0.6, bus "
    "V·I 0x017 on 0.5) between samples: guarantee none, no bound; use envelope metering for a "
    "guarantee (docs/guide/drives.md: ODrive axes)"
)
UNVERIFIED_WARNING = (
    "warning: --odrive-trust-limits: the limits written are taken as written, not read back "
    "(firmware 0.5 cannot read them over CAN); the bound holds only if the axis took them"
)


UNWATCHED_WARNING = (
    "warning: --odrive: the axes' watchdog is not read ({why}): if the supervisor dies an "
    "axis runs on at the limits it last wrote, unguarded, for as long as nothing else stops it "
    "(the status's watchdog says unbounded)"
)


def _endpoints(names: str, example: str) -> Callable[[str], tuple[int, int]]:
    """A parser of ``names``: two endpoint ids (0-65535)."""

    def parse(text: str) -> tuple[int, int]:
        try:
            first, second = (int(part, 0) for part in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{text[:40]!r}: {names}, e.g. {example} (from flat_endpoints.json)"
            ) from None
        if not (0 <= first <= 0xFFFF and 0 <= second <= 0xFFFF):
            raise argparse.ArgumentTypeError(f"{text[:40]!r}: endpoint ids are 0-65535")
        return first, second

    return parse


endpoint_pair = _endpoints("VEL_ID,CURRENT_ID", "401,178")
"""``VEL,CURRENT``: two endpoint ids (0-65535)."""
watchdog_pair = _endpoints("ENABLE_ID,TIMEOUT_ID", "215,216")
"""``ENABLE,TIMEOUT``: the watchdog's two endpoint ids (0-65535)."""


def add_odrive_flags(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group(
        "ODrive axes",
        "guard ODrive axes over CAN Simple (firmware 0.5 or 0.6): each gets a proxy client, its "
        "velocity and current limits are written (Set_Limits) and read back where the firmware "
        "allows, the power they allow is charged by the clock, and Estop and Set_Axis_State "
        "IDLE stop it when its budget runs out; an axis that does not stop is reported STUCK",
    )
    g.add_argument("--odrive", type=node_ids, metavar="IDS", help="axis node ids 1-63, e.g. 3,4")
    g.add_argument(
        "--odrive-firmware",
        choices=FIRMWARES,
        default="0.6",
        help="0.6 reads limits back (--odrive-endpoints) and reports power (0x01D); 0.5 does "
        "neither (default 0.6)",
    )
    g.add_argument(
        "--odrive-endpoints",
        type=endpoint_pair,
        metavar="VEL,CURRENT",
        help="0.6: endpoint ids of axis.controller.config.vel_limit and "
        "axis.config.motor.current_soft_max (flat_endpoints.json of the firmware): the limits "
        "are read back through them",
    )
    g.add_argument(
        "--odrive-watchdog-endpoints",
        type=watchdog_pair,
        metavar="ENABLE,TIMEOUT",
        help="0.6: endpoint ids of axis.config.enable_watchdog and axis.config.watchdog_timeout "
        "(flat_endpoints.json): the watchdog is read at set-up and with every read-back of the "
        "limits; one that is off, longer than --odrive-max-watchdog or unanswered refuses the "
        "axis (without them the status says the watchdog is not read)",
    )
    add_duration(
        g,
        "--odrive-max-watchdog",
        1_000_000,
        "the longest watchdog timeout an axis is taken with (what it may draw after the "
        "supervisor died: its envelope times that)",
        low_us=1_000,
    )
    g.add_argument(
        "--odrive-allow-unwatched",
        action="store_true",
        help="take an axis whose watchdog reads off, too long or unanswered (reported on stderr "
        "and in the status: after the supervisor's exit unbounded)",
    )
    g.add_argument(
        "--odrive-meter",
        choices=("envelope", "sampled"),
        default="envelope",
        help="envelope: the limits' power by the clock, sound; sampled: the axis's power "
        "readings, no guarantee (default envelope)",
    )
    g.add_argument(
        "--odrive-max-speed",
        type=_number("rev/s", 10_000, zero=False),
        metavar="REV_S",
        help="the velocity limit the guard writes (envelope metering)",
    )
    g.add_argument(
        "--odrive-max-current",
        type=_number("A", 1000, zero=False),
        metavar="AMPS",
        help="the current limit the guard writes (envelope metering)",
    )
    g.add_argument(
        "--odrive-torque-constant",
        type=_number("N·m/A", 100, zero=False),
        metavar="NM_PER_A",
        help="the motor's torque constant (8.27 / KV)",
    )
    g.add_argument(
        "--odrive-resistance",
        type=_number("ohms", 1000, zero=True),
        default=Fraction(0),
        metavar="OHMS",
        help="phase resistance (hot): copper losses 3/2·R·i² in the envelope (default 0)",
    )
    g.add_argument(
        "--odrive-vel-tolerance",
        type=_number("", 100, zero=False),
        default=Fraction(6, 5),
        metavar="FACTOR",
        help="the firmware's vel_limit_tolerance: speed may reach it × the velocity limit "
        "(default 1.2)",
    )
    g.add_argument(
        "--odrive-bus-voltage",
        type=_number("V", 1000, zero=True),
        default=Fraction(0),
        metavar="VOLTS",
        help="the supply's highest voltage: the envelope is at most V_bus·i_lim (raised to what "
        "0x017 shows; default 0: from the first reading)",
    )
    g.add_argument(
        "--odrive-trust-limits",
        action="store_true",
        help="take limits that cannot be read back (0.5, or no endpoints) as written",
    )
    g.add_argument(
        "--odrive-reserve",
        type=energy,
        default=0,
        metavar="ENERGY",
        help="kept on top of the bound; the whole margin with sampled metering (default 0)",
    )
    add_duration(g, "--odrive-feedback-timeout", 300_000, "stop an axis not heard this long")
    add_duration(
        g, "--odrive-reaction", 10_000, "host reaction the bound allows (raised to what is seen)"
    )
    add_duration(
        g, "--odrive-latency", 5_000, "axis latency the bound allows (raised to what is seen)"
    )
    add_duration(
        g, "--odrive-stop-timeout", 500_000, "an axis not IDLE this long after a stop is STUCK"
    )


def check_odrive(args: argparse.Namespace) -> None:
    """Everything about the axes that can be judged before the bus is opened."""
    axes = args.odrive or ()
    if not axes:
        return
    if any(n > NODE_MAX for n in axes):
        raise ValueError(f"--odrive: CAN Simple node ids are 1-{NODE_MAX}")
    if args.cia402:
        raise ValueError(
            "--odrive and --cia402 on one bus: CANopen's identifiers are CAN Simple commands "
            "of some axis (e.g. 0x77F is node 59's Enter_DFU_Mode); guard them on two buses"
        )
    if args.canopen:
        raise ValueError("--odrive: not with --canopen (CANopen identifiers are axis commands)")
    if set(axes) & set(args.nodes or ()):
        raise ValueError("a node id is either a canergy node (--nodes) or an axis (--odrive)")
    if args.listen_only:
        raise ValueError("--odrive guards axes and must send: not with --listen-only")
    if args.odrive_watchdog_endpoints is not None and args.odrive_firmware != "0.6":
        raise ValueError(
            "--odrive-watchdog-endpoints: firmware 0.5 has no way to read an endpoint over CAN"
        )
    if args.odrive_watchdog_endpoints is None:
        print(UNWATCHED_WARNING.format(why=_unread(args)), file=sys.stderr)
    if args.odrive_meter == "sampled":
        print(SAMPLED_WARNING, file=sys.stderr)
        return
    flags = ("--odrive-max-speed", "--odrive-max-current", "--odrive-torque-constant")
    missing = [f for f in flags if getattr(args, f[2:].replace("-", "_")) is None]
    if missing:
        raise ValueError(f"--odrive-meter envelope needs {', '.join(missing)}")
    readable = args.odrive_firmware == "0.6" and args.odrive_endpoints is not None
    if not readable and not args.odrive_trust_limits:
        why = (
            "firmware 0.5 has no way to read a limit back over CAN"
            if args.odrive_firmware == "0.5"
            else "0.6 reads the limits back through their endpoint ids: give --odrive-endpoints"
        )
        raise ValueError(f"--odrive: {why}; or take them as written with --odrive-trust-limits")
    if not readable:
        print(UNVERIFIED_WARNING, file=sys.stderr)


@dataclass(frozen=True, slots=True)
class OdriveAxes:
    """``--odrive``: the axes and their guards' and links' configuration
    (``canergy.live.supervisor.build.DeviceGroup``)."""

    nodes: tuple[int, ...]
    guard: DeviceConfig[OdriveLimits]
    link: OdriveLinkConfig
    motor: MotorConstants

    def open(
        self, bus: can.BusABC, now: int, clock: Any, wake: Any = None
    ) -> dict[int, tuple[DeviceGuard[OdriveLimits], OdriveLink]]:
        """A guard and a link per axis (the links' listeners still to be added to a Notifier)."""
        limits = None if self.guard.sampled else self.guard.limits
        axes = {}
        for n in self.nodes:
            guard = DeviceGuard(n, OdriveProfile(self.motor), self.guard, now, secrets.randbits(16))
            link = OdriveLink(bus, n, self.link, limits, clock)
            axes[n] = (guard, link)
        return axes


def odrive_watchdog(args: argparse.Namespace) -> WatchdogPolicy:
    """How the axes' own watchdog is judged (``--odrive-watchdog-endpoints`` and the rest)."""
    return WatchdogPolicy(
        kind="odrive axis.config.enable_watchdog, watchdog_timeout",
        read=args.odrive_watchdog_endpoints is not None,
        max_us=args.odrive_max_watchdog,
        allow=args.odrive_allow_unwatched,
        allow_flag="--odrive-allow-unwatched",
        unread=_unread(args),
    )


def _unread(args: argparse.Namespace) -> str:
    if args.odrive_firmware != "0.6":
        return "firmware 0.5 has no way to read it over CAN"
    return "give --odrive-watchdog-endpoints ENABLE,TIMEOUT to read it"


def odrive_axes(args: argparse.Namespace, timing: Timing) -> OdriveAxes:
    """The ``--odrive*`` flags as the builder takes them."""
    sampled = args.odrive_meter == "sampled"
    limits = OdriveLimits(
        float(args.odrive_max_speed or 0), float(args.odrive_max_current or 0)
    ).wire()
    config = DeviceConfig(
        limits=limits,
        sampled=sampled,
        trust_limits=args.odrive_trust_limits,
        timing=timing,
        reaction_us=args.odrive_reaction,
        latency_us=args.odrive_latency,
        feedback_timeout_us=args.odrive_feedback_timeout,
        stop_timeout_us=args.odrive_stop_timeout,
        reserve_uj=args.odrive_reserve,
        reread_us=REREAD_US,
        watchdog=odrive_watchdog(args),
    )
    link_config = OdriveLinkConfig(
        firmware=args.odrive_firmware,
        endpoints=args.odrive_endpoints,
        watchdog_endpoints=args.odrive_watchdog_endpoints,
        sampled=sampled,
    )
    motor = MotorConstants(
        torque_constant=args.odrive_torque_constant or Fraction(0),
        resistance=args.odrive_resistance,
        vel_tolerance=args.odrive_vel_tolerance,
        bus_voltage=args.odrive_bus_voltage,
    )
    return OdriveAxes(tuple(args.odrive), config, link_config, motor)
