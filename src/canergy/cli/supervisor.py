"""``canergy supervisor``: grant energy to client nodes on a CAN bus (one bus, or several
with ``--bus``)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from canergy.argtypes import add_duration, energy, node_ids
from canergy.cli.shared.bus_flags import bus_where, open_bus, open_bus_at
from canergy.cli.shared.buses import BUS_SYNTAX, bus_spec, check_buses
from canergy.cli.shared.cia402 import add_cia402_flags, check_cia402, cia402_drives
from canergy.cli.shared.live import (
    add_on_stuck_flag,
    auth_config,
    auth_key,
    check_on_stuck,
    check_state,
    check_widths,
    core_config,
    grant_limits,
    joules,
    rule_timing,
    service_flags,
    start_without_flag,
    supervisor_flags,
)
from canergy.cli.shared.mit import SIDE_FILTER, add_supervisor_mit_flags, check_mit, mit_group
from canergy.cli.shared.moteus import (
    add_moteus_flags,
    check_moteus,
    moteus_controllers,
    moteus_filters,
)
from canergy.cli.shared.odrive import add_odrive_flags, check_odrive, odrive_axes
from canergy.cli.summaries import SUMMARIES
from canergy.codec import Codec
from canergy.core.supervisor import SupervisorCore
from canergy.live.atomic import warn_no_fsync
from canergy.live.serve import serve_supervisor
from canergy.live.supervisor.build import (
    CanopenConfig,
    DeviceGroup,
    SupervisorConfig,
    build_supervisor,
    check_session_keys,
    open_core,
)
from canergy.live.supervisor.multi_bus import BusSpec, session_keys
from canergy.live.supervisor.policy import TopUp
from canergy.live.supervisor.service import ServiceConfig, SupervisorService
from canergy.live.supervisor.witness import RETURN_HOLD_MIN_US
from canergy.messages import QUANTUM_UJ

EXIT_INTRUSION = 3


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "supervisor",
        help=SUMMARIES["supervisor"],
        description="Run the supervisor: keep nodes topped up and/or serve one-shot grants. "
        "SIGINT/SIGTERM stop it cleanly (open transactions settle or are written off).",
    )
    p.add_argument("--nodes", type=node_ids, help="canergy node ids on the -i/-c bus, e.g. 1-5,9")
    p.add_argument(
        "--bus",
        action="append",
        type=bus_spec,
        metavar=BUS_SYNTAX,
        help="instead of -i/-c/--nodes: one bus and its nodes, e.g. --bus socketcan:can0:1-40 "
        "--bus socketcan:can1:1-127; repeat for every bus. All share one budget; nodes are "
        "named BUS/NODE (can1/5) in the status, the control socket and --state. NAME defaults "
        "to the channel; bit rates, --fd, --timing, --bus-kwargs and --id-base apply to every "
        "bus",
    )
    supervisor_flags(p)
    start_without_flag(p)
    service_flags(p)
    p.add_argument(
        "--inject",
        type=energy,
        metavar="ENERGY",
        help="add this energy to the usable budget, counted as injected, once at start: it is "
        "saved in --state before anything is granted (e.g. 5J; not with --listen-only)",
    )
    p.add_argument(
        "--listen-only",
        action="store_true",
        help="watch and report, never send; without --status-file the status on stdout is one "
        "line per --status-period: frames, nodes talking and silent, their levels, decode "
        "errors, intrusions",
    )
    p.add_argument(
        "--on-intrusion",
        choices=["warn", "stop"],
        default="warn",
        help="a frame only this supervisor sends, from someone else (a second supervisor, a "
        "spoofer): warn = count, log and report it; stop = also grant nothing more, settle and "
        "exit with status 3 (default warn)",
    )
    add_duration(
        p,
        "--return-hold",
        500_000,
        "without --auth: credit a RETURN only once the node's own TELEMETRY confirms it and this "
        "long has passed with no report of frames in its name (a forged RETURN is refuted, "
        "never credited; shorter, the node could not refute one in time)",
        low_us=RETURN_HOLD_MIN_US,
    )
    p.add_argument(
        "--canopen",
        action="store_true",
        help="use CANopen on the same bus: NMT start, heartbeat watchdog, boot-up, SDO audit",
    )
    add_duration(
        p,
        "--heartbeat-timeout",
        3_000_000,
        "--canopen: a node is lost after this long without a heartbeat",
    )
    p.add_argument("--eds", type=Path, help="the nodes' EDS (default: canergy's node EDS)")
    add_cia402_flags(p)
    add_odrive_flags(p)
    add_moteus_flags(p)
    add_supervisor_mit_flags(p)
    add_on_stuck_flag(p, "ODrive axis, moteus controller or MIT-mode motor")
    p.set_defaults(run=run)


def _check_eds(path: Path | None) -> None:
    """The nodes' object dictionary loads, before anything is written or sent."""
    import canopen

    from canergy.live.canopen.shared_bus import EDS

    try:
        canopen.import_od(str(path or EDS))
    except Exception as exc:  # canopen raises what its parsers raise
        raise ValueError(f"--eds {path}: not a usable EDS ({exc})") from None


def _buses(args: argparse.Namespace) -> tuple[BusSpec, ...]:
    """The ``--bus`` options, checked against each other and the rest (none without --bus)."""
    specs = tuple(args.bus or ())
    if not specs:
        return ()
    given = [
        flag
        for flag, dest in (("-i/--interface", "interface"), ("-c/--channel", "channel"))
        if getattr(args, dest, None) is not None
    ] + ["--nodes"] * (args.nodes is not None)
    if given:
        raise ValueError(
            f"--bus names each bus's interface, channel and nodes: not with {', '.join(given)}"
        )
    single = [
        flag
        for flag, on in (
            ("--canopen", args.canopen),
            ("--cia402", args.cia402),
            ("--odrive", args.odrive),
            ("--moteus", args.moteus),
            ("--mit", args.mit),
        )
        if on
    ]
    if single:
        raise ValueError(f"{' and '.join(single)} work on one bus (-i/-c/--nodes), not with --bus")
    check_buses(specs)
    if args.auth is not None:  # the builder's refusal (one master key: a node's key is its id's)
        check_session_keys([spec.name for spec in specs], session_keys(specs), _by_id)
    return specs


def _by_id(bus: int, node: int) -> bytes:
    """A node's key under ``--auth``, as far as telling two apart goes: one master key on every
    bus, so its id alone (checked before the key file is read)."""
    return bytes([node])


def _announce(args: argparse.Namespace, service: SupervisorService) -> None:
    warn_no_fsync("canergy supervisor", args.no_fsync)
    if service.ledger.injected_this_run:
        st, added = service.core.state, joules(service.ledger.injected_this_run)
        print(
            f"canergy supervisor: injected {added} into the budget, saved in {args.state}: "
            f"usable {joules(st.usable)}, injected in all {joules(st.injected)}",
            file=sys.stderr,
        )


def _report_axis(line: str) -> None:
    print(f"canergy supervisor: {line}", file=sys.stderr, flush=True)


def _exit_status(service: SupervisorService) -> int:
    if not service.stopped_by_intrusion:
        return 0
    report = service.intrusions.as_json()
    print(
        f"canergy supervisor: stopped on intrusion (--on-intrusion stop): "
        f"{report['total']} foreign frame(s), first {report['recent'][0]['frame']}",
        file=sys.stderr,
    )
    return EXIT_INTRUSION


def run(args: argparse.Namespace) -> int:
    buses = _check(args)
    key = auth_key(args)
    if args.canopen:
        _check_eds(args.eds)
    config = supervisor_config(args, buses, key)
    core = open_core(config)  # the books are read (or refused) before a bus is opened
    if buses:
        return _run_buses(args, buses, config, core)
    return _run_bus(args, config, core)


def _check(args: argparse.Namespace) -> tuple[BusSpec, ...]:
    """Every value checked against the others before anything is read, written or opened;
    the ``--bus`` options (none on one bus)."""
    buses = _buses(args)
    if args.on_stuck is not None and not (args.odrive or args.moteus or args.mit):
        raise ValueError(
            "--on-stuck is for guarded ODrive axes, moteus controllers or MIT-mode motors"
        )
    check_on_stuck(args)
    if args.target is not None and args.target < QUANTUM_UJ:
        raise ValueError("--target must be at least 1 mJ")
    check_widths(args)
    if args.inject is not None and (args.listen_only or args.inject <= 0):
        raise ValueError(
            "--inject needs an energy above 0 and a supervisor that sends and keeps "
            "its --state (not --listen-only)"
        )
    if not buses:
        check_mit(args)
        check_moteus(args)
        check_odrive(args)
        check_cia402(args)
    check_state(args, required=not args.listen_only)
    return buses


def _devices(args: argparse.Namespace) -> tuple[DeviceGroup, ...]:
    """The guarded device groups asked for, one per profile flag (``--odrive``, ``--moteus``,
    ``--mit``)."""
    timing = rule_timing(args)
    groups: list[DeviceGroup] = []
    if args.odrive:
        groups.append(odrive_axes(args, timing))
    if args.moteus:
        groups.append(moteus_controllers(args, timing))
    if args.mit:
        groups.append(mit_group(args, timing))
    return tuple(groups)


def supervisor_config(
    args: argparse.Namespace, buses: tuple[BusSpec, ...], key: Any
) -> SupervisorConfig:
    """The flags, checked, as the builder takes them: the one place they become a
    ``SupervisorConfig``."""
    names = tuple(spec.name for spec in buses)
    devices = _devices(args)
    guarded = (*(args.cia402 or ()), *(n for group in devices for n in group.nodes))
    nodes = session_keys(buses) if buses else tuple(sorted((*(args.nodes or ()), *guarded)))
    listening = args.listen_only and args.status_file is None
    service = ServiceConfig(
        policy=TopUp(args.target, args.min_grant) if args.target is not None else None,
        limits=grant_limits(args),
        state_path=args.state,
        status_path=args.status_file,
        status_stream=sys.stdout if args.status_file is None else None,
        status_text=listening_line(", ".join(names) or _channel(args)) if listening else None,
        status_period_us=args.status_period,
        lost_after_us=args.lost_after,
        stop_timeout_us=args.stop_timeout,
        listen_only=args.listen_only,
        fsync=not args.no_fsync,
        inject_uj=args.inject or 0,
        stop_on_intrusion=args.on_intrusion == "stop",
        return_hold_us=None if key is not None else args.return_hold,
        local_nodes=frozenset(guarded),
        bus_names=names,
    )
    canopen = None
    if args.canopen:
        from canergy.live.canopen.shared_bus import EDS

        canopen = CanopenConfig(tuple(args.nodes), args.eds or EDS, args.heartbeat_timeout)
    return SupervisorConfig(
        core=core_config(args, nodes),
        service=service,
        id_base=args.id_base,
        auth=auth_config(args, key),
        control_path=args.control,
        canopen=canopen,
        cia402=cia402_drives(args, rule_timing(args)) if args.cia402 else None,
        devices=devices,
        report=_report_axis,
        on_stuck=args.on_stuck,
    )


def _channel(args: argparse.Namespace) -> str:
    channel, interface = bus_where(args)
    return channel or interface or "the bus"


def listening_line(where: str) -> Callable[[dict[str, Any]], str]:
    """``--listen-only``'s status on stdout: who talks (heard within --lost-after) and what
    fails to decode, one line, e.g. ``listening on can0: 1234 frames, nodes talking 1-4, silent
    5, levels 3.200 J, decode errors 0, intrusions 0``; with ``, a supervisor's frames 612`` when
    a supervisor grants on the bus (frames in its direction: no intrusion to a listener)."""

    def line(status: dict[str, Any]) -> str:
        nodes: dict[str, dict[str, Any]] = status["nodes"]
        talking = [name for name, n in nodes.items() if not n["lost"]]
        silent = [name for name, n in nodes.items() if n["lost"]]
        levels = sum(nodes[name]["level_uj"] or 0 for name in talking)
        reasons: dict[str, int] = status["decode_error_reasons"]
        why = ", ".join(f"{r} {n}" for r, n in sorted(reasons.items()))
        parts = [
            f"{status['frames_received']} frames",
            f"nodes talking {_names(talking) or 'none'}",
            f"silent {_names(silent) or 'none'}",
            f"levels {levels / 1e6:.3f} J",
            f"decode errors {status['decode_errors']}" + (f" ({why})" if why else ""),
            f"intrusions {status['intrusions']}",
        ]
        if seen := sum(n["supervisor_frames"] for n in nodes.values()):
            parts.append(f"a supervisor's frames {seen}")
        if status.get("stopping"):
            parts.append("stopping")
        return f"listening on {where}: {', '.join(parts)}"

    return line


def _names(names: list[str]) -> str:
    """Node names as ranges, ``1-3,5`` (several buses: ``can0/1-3,can1/5``)."""
    runs: list[tuple[str, int, int]] = []
    for name in sorted(names, key=lambda n: (n.rpartition("/")[0], int(n.rpartition("/")[2]))):
        bus, _, number = name.rpartition("/")
        node = int(number)
        if runs and runs[-1][0] == bus and runs[-1][2] == node - 1:
            runs[-1] = (bus, runs[-1][1], node)
        else:
            runs.append((bus, node, node))
    return ",".join(
        f"{bus + '/' if bus else ''}{a}" + (f"-{b}" if b != a else "") for bus, a, b in runs
    )


def _run_bus(args: argparse.Namespace, config: SupervisorConfig, core: SupervisorCore) -> int:
    """One bus (-i/-c/--nodes), with CANopen and guarded drives and devices if asked for."""
    filters = Codec(args.id_base).supervisor_watch_filters()
    if config.shares_bus:
        from canergy.live.canopen.shared_bus import STANDARD_FRAMES

        filters.append(STANDARD_FRAMES)  # CANopen's 11-bit ids
    if args.moteus:
        from canergy.live.canopen.shared_bus import STANDARD_FRAMES

        filters += [STANDARD_FRAMES, *moteus_filters(args)]
    if args.mit:
        filters.append(SIDE_FILTER)  # CubeMars servo-mode frames (the 11-bit ones pass above)
    bus = open_bus(args, filters)
    try:
        built = build_supervisor(config, [bus], core=core)
        try:
            _announce(args, built.service)
            serve_supervisor(
                built.loop, built.service, built.control, manager=built.manager, exit=built.exit
            )
            return _exit_status(built.service)
        finally:
            built.close()
    finally:
        bus.shutdown()


def _run_buses(
    args: argparse.Namespace,
    specs: tuple[BusSpec, ...],
    config: SupervisorConfig,
    core: SupervisorCore,
) -> int:
    """``--bus``: one service over every bus, a runtime per bus, one loop for them all."""
    codec = Codec(args.id_base)
    opened: list[Any] = []
    try:
        for spec in specs:
            filters = codec.supervisor_watch_filters()
            opened.append(open_bus_at(args, spec.interface, spec.channel, filters, spec.name))
        built = build_supervisor(config, opened, core=core)
        try:
            _announce(args, built.service)
            serve_supervisor(built.loop, built.service, built.control)
            return _exit_status(built.service)
        finally:
            built.close()
    finally:
        for bus in opened:
            bus.shutdown()
