"""``canergy gateway``: a client of the supervisor above, the supervisor of the bus below."""

from __future__ import annotations

import argparse
import random
import secrets
import sys
from typing import Any

from canergy.cli_args import add_duration, bounded_int, energy, node_ids, probability, seed
from canergy.cli_live import (
    _check_state,
    _check_widths,
    _limits,
    _serve,
    _timing,
    book_flags,
    service_flags,
)
from canergy.codec import Codec
from canergy.core.gateway import Gateway
from canergy.core.state import Phase
from canergy.faults import FaultInjector, FaultProfile
from canergy.live.bus_args import add_bus_flags, open_bus
from canergy.live.bus_group import BusGroup
from canergy.live.control import ControlServer
from canergy.live.gateway import DownstreamService, GatewayFiles, Uplink, UplinkConfig
from canergy.live.gateway_state import load_gateway
from canergy.live.policy import TopUp
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.live.service import ServiceConfig
from canergy.messages import QUANTUM_UJ, Direction

UP = "upstream"


def add_parsers(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "gateway",
        help="a client of the supervisor above and the supervisor of the bus below",
        description="Run a gateway: node --node on the upstream bus (--upstream-* flags, e.g. "
        "--upstream-interface zenoh), supervisor of --nodes on the downstream bus (-i/-c ...). "
        "Energy committed to it upstream becomes its downstream budget at once; what it holds "
        "above --return-above goes back upstream as numbered returns. One --state file keeps "
        "both roles. SIGINT/SIGTERM stop it cleanly.",
    )
    p.add_argument("--node", type=bounded_int(1, 127), required=True, help="its id upstream")
    p.add_argument("--nodes", type=node_ids, required=True, help="downstream node ids, e.g. 1-40")
    add_bus_flags(p)
    add_bus_flags(p, prefix=UP)
    book_flags(p)
    service_flags(p)
    p.add_argument(
        "--return-above",
        type=energy,
        help="return the downstream usable budget above this upstream (default: keep it); keep "
        "it above the --target the supervisor above gives this gateway, or the two would pass "
        "the same energy back and forth",
    )
    add_duration(p, "--telemetry-period", 100_000, "time between level reports upstream")
    add_duration(
        p,
        "--upstream-response-timeout",
        50_000,
        "the response timeout of the supervisor above (the gateway waits twice that for a command)",
    )
    for kind in ("loss", "duplicate", "reorder"):
        p.add_argument(
            f"--upstream-{kind}",
            type=probability,
            default=0.0,
            help=f"tests and soak runs: {kind} this fraction of the frames sent upstream",
        )
    p.add_argument("--fault-seed", type=seed, default=0, help="seed of the upstream faults")


def _build(args: argparse.Namespace, now: int) -> tuple[Gateway, bool]:
    """The gateway core from its state file; True when it has no upstream books (a JOIN)."""
    nodes = tuple(args.nodes)
    state = None
    if args.state.exists():
        state = load_gateway(
            args.state,
            "hardened",
            args.node,
            nodes,
            accept_edited=args.accept_edited_state,
            on_edited=lambda why: print(f"canergy gateway: warning: {why}", file=sys.stderr),
        )
    gateway = Gateway(
        args.node,
        nodes,
        up_timing=_timing(args, args.upstream_response_timeout),
        down_timing=_timing(args),
        state=state,
    )
    if state is None:
        return gateway, True
    joining = state.up.phase is Phase.JOINING
    gateway.power_loss(now)  # a start is a restart from the one record
    return gateway, joining


def _upstream_bus(args: argparse.Namespace, codec: Codec) -> Any:
    bus = open_bus(args, codec.client_watch_filters(args.node), prefix=UP)
    profile = FaultProfile(
        loss=args.upstream_loss, duplicate=args.upstream_duplicate, reorder=args.upstream_reorder
    )
    if not (profile.loss or profile.duplicate or profile.reorder):
        return bus
    from canergy.live.faulty_bus import FaultyBus

    return FaultyBus(bus, FaultInjector(profile, random.Random(args.fault_seed)))


def _check_buses(args: argparse.Namespace) -> None:
    """The two legs are two buses (or two identifier blocks of one): a gateway that heard its
    own downstream frames as its upstream supervisor's would credit itself."""

    def flag(name: str) -> object:  # python-can leaves an option not given unset
        return getattr(args, name, None)

    same = (
        flag("interface") == flag("upstream_interface")
        and flag("channel") == flag("upstream_channel")
        and args.id_base == args.upstream_id_base
    )
    if same:
        raise ValueError(
            "the upstream and downstream buses are the same bus and identifier block: give "
            "--upstream-channel another bus (or --upstream-id-base another block)"
        )


def run_gateway(args: argparse.Namespace) -> int:
    if args.target is not None and args.target < QUANTUM_UJ:
        raise ValueError("--target must be at least 1 mJ")
    _check_buses(args)
    _check_widths(args)
    _check_state(args)
    now = monotonic_us()
    gateway, without_books = _build(args, now)
    files = GatewayFiles(gateway, args.state, fsync=not args.no_fsync)
    config = ServiceConfig(
        policy=TopUp(args.target, args.min_grant) if args.target is not None else None,
        limits=_limits(args),
        status_path=args.status_file,
        status_stream=sys.stdout if args.status_file is None else None,
        status_period_us=args.status_period,
        lost_after_us=args.lost_after,
        stop_timeout_us=args.stop_timeout,
        fsync=not args.no_fsync,
    )
    down_codec, up_codec = Codec(args.id_base), Codec(args.upstream_id_base)
    down_bus = open_bus(args, down_codec.supervisor_watch_filters())
    up_bus = None
    control = None
    group = None
    try:
        up_bus = _upstream_bus(args, up_codec)
        control = ControlServer(args.control) if args.control is not None else None
        uplink = Uplink(
            gateway,
            UplinkConfig(telemetry_period_us=args.telemetry_period, return_above=args.return_above),
            files,
            now,
        )
        if without_books:  # JOINING before the first save: a blank record is never trusted
            uplink.start_without_books(secrets.randbits(16), now)
        service = DownstreamService(gateway.down, config, now, save=files.save)  # saves once
        service.uplink = uplink
        up = BusRuntime(up_bus, uplink, codec=up_codec, receives=Direction.TO_CLIENT)
        down = BusRuntime(down_bus, service, codec=down_codec, receives=Direction.TO_SUPERVISOR)
        uplink.counters, service.bus_counters = up.counters, down.counters
        group = BusGroup([up, down])
        _serve(group, service, control)
    finally:
        if group is not None:
            group.close()
        if control is not None:
            control.close()
        for bus in (up_bus, down_bus):
            if bus is not None:
                bus.shutdown()
    return 0


COMMANDS = {"gateway": run_gateway}
