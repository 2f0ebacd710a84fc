"""``canergy supervisor`` and ``canergy grant``: the supervisor on a real (or virtual) bus."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from canergy.auth.state_key import state_seal
from canergy.cli_args import add_duration, bounded_int, energy, grant_amount, node_ids, power
from canergy.cli_cia402 import add_cia402_flags, check_cia402, guard_drives
from canergy.codec import Codec
from canergy.core import Supervisor, Timing
from canergy.core.variants import VARIANTS
from canergy.live.atomic import check_writable_dir, same_file
from canergy.live.bus_args import BusOpenError, add_bus_flags, open_bus, open_bus_at
from canergy.live.bus_group import BusGroup
from canergy.live.bus_keys import parse_node_id, parse_node_name
from canergy.live.control import ControlServer, check_control_path, request
from canergy.live.multi_bus import (
    BUS_SYNTAX,
    BusPort,
    BusRouter,
    BusSpec,
    bus_spec,
    check_buses,
    session_keys,
)
from canergy.live.policy import Limits, TopUp, level_room
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.live.service import ServiceConfig, SupervisorService
from canergy.live.state_file import ACCEPT_EDITED, books_nodes, keep_books, load_state
from canergy.messages import AMOUNT_MAX_MJ, QUANTUM_UJ, USABLE_MAX_UJ, Direction, Message
from canergy.units import UJ_PER_J, US_PER_S, format_energy

__all__ = ["COMMANDS", "BusOpenError", "add_parsers"]

_LARGEST_GRANT = AMOUNT_MAX_MJ * QUANTUM_UJ
EXIT_INTRUSION = 3


def _joules(uj: int) -> str:
    return format_energy(uj).replace(" ", "")


_ROOM = f"{_joules(USABLE_MAX_UJ)} (what a node's record holds) minus --max-grant"


def _supervisor_flags(p: argparse.ArgumentParser) -> None:
    add_bus_flags(p)
    p.add_argument("--variant", choices=sorted(VARIANTS), default="hardened")
    p.add_argument("--initial", type=energy, default=10 * UJ_PER_J, help="budget of a new state")
    book_flags(p)
    p.add_argument(
        "--auth",
        type=Path,
        metavar="KEYFILE",
        help="authenticated mode with this master key (`canergy keys master`, mode 0600): every "
        "frame carries a truncated AES-CMAC; with --fd one CAN FD frame and a 64-bit MAC, "
        "otherwise each frame is followed by a MAC frame (40-bit MAC)",
    )


def book_flags(p: argparse.ArgumentParser) -> None:
    """The flags of a supervisor's books, limits and timing (a gateway's downstream too)."""
    p.add_argument("--state", type=Path, help="non-volatile state file (created if missing)")
    p.add_argument(
        ACCEPT_EDITED,
        action="store_true",
        help="take a --state file whose checksum is missing or wrong (edited by hand, or "
        "written by an older canergy) if it passes every other check; the next save writes a "
        "fresh checksum",
    )
    p.add_argument("--no-fsync", action="store_true", help="skip fsync of the state file (tests)")
    add_duration(p, "--response-timeout", 50_000, "wait this long for a reply")
    p.add_argument("--retries", type=bounded_int(0, 100), default=3)
    p.add_argument(
        "--max-grant",
        type=energy,
        default=_LARGEST_GRANT,
        help=f"largest grant per transaction (default and at most {_joules(_LARGEST_GRANT)}, what "
        "one frame carries)",
    )
    p.add_argument(
        "--max-node-level",
        type=energy,
        help=f"never lift a node's level above this; at most {_ROOM}, room for a written-off "
        "grant paid back on top",
    )
    p.add_argument("--max-total", type=energy, help="energy granted in this run, all nodes")
    p.add_argument("--rate", type=power, help="sustained grant rate over all nodes, e.g. 2W")
    add_duration(p, "--stop-timeout", 5_000_000, "time to settle on exit")


def service_flags(p: argparse.ArgumentParser) -> None:
    """Top-up policy, liveness, status and control of a running supervisor (or gateway)."""
    p.add_argument(
        "--target",
        type=energy,
        help=f"top each node up to this reported level; at most {_ROOM} (see --max-node-level)",
    )
    p.add_argument("--min-grant", type=energy, default=QUANTUM_UJ, help="smallest top-up")
    add_duration(p, "--lost-after", 3_000_000, "a node is lost after this long without a frame")
    p.add_argument("--status-file", type=Path, help="JSON status (default: JSON lines on stdout)")
    add_duration(p, "--status-period", 1_000_000, "time between status reports")
    p.add_argument(
        "--control",
        type=Path,
        help="UNIX socket for `canergy grant --control`; replaces only a stale socket, removed "
        "at exit",
    )


def add_parsers(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "supervisor",
        help="grant energy to client nodes on a CAN bus",
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
    _supervisor_flags(p)
    service_flags(p)
    p.add_argument(
        "--inject",
        type=energy,
        metavar="ENERGY",
        help="add this energy to the usable budget, counted as injected, once at start: it is "
        "saved in --state before anything is granted (e.g. 5J; not with --listen-only)",
    )
    p.add_argument("--listen-only", action="store_true", help="watch and report, never send")
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
        "never credited)",
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

    g = sub.add_parser(
        "grant",
        help="one grant: through a running supervisor (--control) or as a single run",
        description="Grant energy to one node. With --control, ask a running supervisor; "
        "otherwise run a supervisor on the bus for this one transaction. Exit 0 when committed.",
    )
    g.add_argument(
        "--node",
        type=_grant_node,
        required=True,
        help="node id 1-127; with --control, BUS/NODE (e.g. can1/5) names a node of a "
        "supervisor over several buses (--bus)",
    )
    g.add_argument("--amount", type=grant_amount, required=True, help="e.g. 2J (1 mJ to 65.535 J)")
    g.add_argument("--control", type=Path, help="socket of a running supervisor")
    add_duration(g, "--timeout", 10_000_000, "wait this long for the end")
    _supervisor_flags(g)


def _grant_node(text: str) -> int | str:
    """``grant --node``: an id, or ``BUS/NODE`` (checked by the supervisor that has buses)."""
    bus, sep, node = text.rpartition("/")
    if not sep:
        return bounded_int(1, 127)(text)
    if not bus or parse_node_id(node) is None:
        raise argparse.ArgumentTypeError(f"{text[:40]!r}: expected a node id 1-127 or BUS/NODE")
    return text


def _timing(args: argparse.Namespace, response_timeout_us: int | None = None) -> Timing:
    """The rules' timing from ``--response-timeout`` (or ``response_timeout_us``) and
    ``--retries``: a node waits twice the response timeout for a command or a RETURN_ACK."""
    timeout = args.response_timeout if response_timeout_us is None else response_timeout_us
    return Timing(
        response_timeout_us=timeout,
        retries=args.retries,
        command_timeout_us=2 * timeout,
        return_retry_us=2 * timeout,
    )


def _build(
    args: argparse.Namespace, nodes: tuple[int, ...], buses: tuple[str, ...] = (), key: Any = None
) -> Supervisor:
    """The core, from ``--state`` when it exists; ``buses``: bus names with ``--bus`` (``nodes``
    are then session keys); ``key``: ``--auth``'s, which seals the state file."""
    timing = _timing(args)
    state = None
    seal = None if key is None else state_seal(key)
    if args.state is not None and args.state.exists():

        def warn(message: str) -> None:
            print(f"canergy {args.command}: warning: {message}", file=sys.stderr)

        state = load_state(
            args.state,
            args.variant,
            nodes,
            buses=buses,
            accept_edited=args.accept_edited_state,
            on_edited=warn,
            seal=seal,
        )
    if args.state is not None and not getattr(args, "listen_only", False):
        keep_books(args.state, seal, args.auth, fresh=state is None)
    core = Supervisor(nodes, args.initial, variant=args.variant, timing=timing, state=state)
    if state is not None:
        core.power_loss(monotonic_us())  # a start is a restart from the persistent record
    return core


def _limits(args: argparse.Namespace) -> Limits:
    return Limits(
        max_grant=args.max_grant,
        max_node_level=args.max_node_level,
        max_total=args.max_total,
        rate_uj_per_s=args.rate,
    )


def _auth_key(args: argparse.Namespace) -> Any:
    """``--auth``'s master key, checked before anything is written or opened."""
    if args.auth is None:
        return None
    from canergy.auth.keys import load_key

    key = load_key(args.auth)
    if key.kind != "master":
        raise ValueError(f"--auth {args.auth}: a supervisor needs the master key, not a node key")
    if args.variant != "hardened":
        raise ValueError("--auth needs the hardened rules (--variant hardened)")
    return key


def _auth(
    args: argparse.Namespace,
    key: Any,
    codec: Codec,
    freshness: Callable[[Message], int | None],
) -> Any:
    """The frame authenticator for ``--auth`` (None without it); ``freshness``: the service's
    (or its port's, over several buses)."""
    if key is None:
        return None
    from canergy.auth.frames import FrameAuth, Layout
    from canergy.auth.keys import frame_auth_keys

    layout = Layout.FD if getattr(args, "fd", False) else Layout.CLASSIC
    return FrameAuth(codec, layout, frame_auth_keys(key), Direction.TO_SUPERVISOR, freshness)


def _check_eds(path: Path | None) -> None:
    """The nodes' object dictionary loads, before anything is written or sent."""
    import canopen

    from canergy.live.shared_bus import EDS

    try:
        canopen.import_od(str(path or EDS))
    except Exception as exc:  # canopen raises what its parsers raise
        raise ValueError(f"--eds {path}: not a usable EDS ({exc})") from None


def _canopen(args: argparse.Namespace, bus: Any, service: SupervisorService) -> tuple[Any, Any]:
    from canergy.live.canopen_manager import CanopenManager
    from canergy.live.shared_bus import EDS, shared_network

    network, reader = shared_network(bus)
    try:
        manager = CanopenManager(
            network, args.nodes, args.eds or EDS, args.heartbeat_timeout, monotonic_us
        )
    except BaseException:  # e.g. an --eds that is not an EDS: no Notifier thread left behind
        if network.notifier is not None:
            network.notifier.stop()
        raise
    service.liveness = manager.alive
    if not args.listen_only:
        manager.start_all()
    return manager, reader


class _Loop(Protocol):
    def poll(self, max_wait_s: float = 0.1) -> None: ...


def _serve(
    runtime: _Loop,
    service: SupervisorService,
    control: ControlServer | None,
    until: Any = None,
    manager: Any = None,
) -> None:
    """Loop until a signal (or ``until()``) and the service has settled."""

    def request_stop(signum: int, frame: object) -> None:
        service.stop(monotonic_us())

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, request_stop)
        signal.signal(signal.SIGTERM, request_stop)
    while not service.finished(monotonic_us()):
        runtime.poll(0.05)
        if manager is not None and not service.config.listen_only:
            for node in manager.rebooted():
                service.node_rebooted(node, monotonic_us())
        if control is not None:
            for req, reply in control.pending():
                _control_request(service, req, reply, manager)
        if until is not None and until():
            service.stop(monotonic_us())
    service.write_status()


def _control_request(
    service: SupervisorService, req: dict[str, Any], reply: Any, manager: Any = None
) -> None:
    if req.get("audit") is True:
        if manager is None:
            reply({"error": "the SDO audit needs --canopen"})
            return
        # SDO reads block: answer from a thread while the loop keeps running
        audit = manager.audit
        threading.Thread(target=lambda: reply(audit(service.books)), daemon=True).start()
        return
    if req.get("status") is True:
        reply(service.status())
        return
    if req.get("stop") is True:
        service.stop(monotonic_us())
        reply({"stopping": True})
        return
    grant = req.get("grant")
    if not isinstance(grant, dict):
        reply(
            {
                "error": 'expected {"grant": {"node": N, "amount_uj": A}}, {"status": true} or '
                '{"stop": true}'
            }
        )
        return
    node, amount = grant.get("node"), grant.get("amount_uj")
    buses = service.config.bus_names
    if not isinstance(amount, int) or isinstance(amount, bool) or amount <= 0:
        reply({"error": "amount_uj must be a positive integer"})
        return
    try:
        key = parse_node_name(buses, node)
    except ValueError as exc:
        reply({"error": str(exc)})
        return
    service.request_grant(key, amount, reply)


def _check_state(args: argparse.Namespace, *, required: bool = True) -> None:
    """``--state`` is given (when ``required``); every file the run writes can be written, none
    is another under a second name, and ``--control`` replaces nothing but a stale socket.
    Reads and writes nothing."""
    if args.state is None and required:
        raise ValueError(
            "--state PATH is required: without its non-volatile record a restarted supervisor "
            "would reuse transaction numbers and grant its budget again"
        )
    outputs = [
        (option, path)
        for option, path in (
            ("--state", args.state),
            ("--status-file", getattr(args, "status_file", None)),
            ("--control", args.control if args.command != "grant" else None),
        )
        if path is not None
    ]
    for i, (option, path) in enumerate(outputs):
        for other, other_path in outputs[:i]:
            if same_file(path, other_path):
                raise ValueError(
                    f"{option} {path} and {other} {other_path} name the same file; "
                    "give each its own path"
                )
    for option, path in outputs:
        check_writable_dir(path, option)
        if option == "--control":
            check_control_path(path, option)


def _check_widths(args: argparse.Namespace) -> None:
    """No configuration may plan a node above what its record holds (``USABLE_MAX_UJ``)."""
    if not QUANTUM_UJ <= args.max_grant <= _LARGEST_GRANT:
        raise ValueError(
            f"--max-grant {_joules(args.max_grant)} must be {_joules(QUANTUM_UJ)} to "
            f"{_joules(_LARGEST_GRANT)}, what one frame carries"
        )
    room = level_room(args.max_grant)
    for option, value in (
        ("--target", getattr(args, "target", None)),
        ("--max-node-level", args.max_node_level),
    ):
        if value is not None and value > room:
            raise ValueError(
                f"{option} {_joules(value)} is above {_joules(room)}: a node's record holds at "
                f"most {_joules(USABLE_MAX_UJ)}, and a written-off grant (--max-grant "
                f"{_joules(args.max_grant)}) may be paid back on top"
            )


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
    single = [flag for flag, on in (("--canopen", args.canopen), ("--cia402", args.cia402)) if on]
    if single:
        raise ValueError(f"{' and '.join(single)} work on one bus (-i/-c/--nodes), not with --bus")
    check_buses(specs)
    if args.auth is not None:
        seen: dict[int, str] = {}
        for spec in specs:
            for node in spec.nodes:
                if node in seen:
                    raise ValueError(
                        f"--auth: node {node} is on bus {seen[node]} and on bus {spec.name}, and "
                        "a node's key comes from its id alone: one could pass for the other; "
                        "give every node a different id"
                    )
                seen[node] = spec.name
    return specs


def _announce(args: argparse.Namespace, service: SupervisorService) -> None:
    if service.injected_this_run:
        st, added = service.core.state, _joules(service.injected_this_run)
        print(
            f"canergy supervisor: injected {added} into the budget, saved in {args.state}: "
            f"usable {_joules(st.usable)}, injected in all {_joules(st.injected)}",
            file=sys.stderr,
        )


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


def run_supervisor(args: argparse.Namespace) -> int:
    buses = _buses(args)
    if args.target is not None and args.target < QUANTUM_UJ:
        raise ValueError("--target must be at least 1 mJ")
    _check_widths(args)
    if args.inject is not None and (args.listen_only or args.inject <= 0):
        raise ValueError(
            "--inject needs an energy above 0 and a supervisor that sends and keeps "
            "its --state (not --listen-only)"
        )
    if not buses:
        check_cia402(args)
    _check_state(args, required=not args.listen_only)
    key = _auth_key(args)
    if args.canopen:
        _check_eds(args.eds)
    names = tuple(spec.name for spec in buses)
    if buses:
        nodes = session_keys(buses)
    else:
        nodes = tuple(sorted((*(args.nodes or ()), *(args.cia402 or ()))))
    core = _build(args, nodes, names, key)
    config = ServiceConfig(
        policy=TopUp(args.target, args.min_grant) if args.target is not None else None,
        limits=_limits(args),
        state_path=args.state,
        status_path=args.status_file,
        status_stream=sys.stdout if args.status_file is None else None,
        status_period_us=args.status_period,
        lost_after_us=args.lost_after,
        stop_timeout_us=args.stop_timeout,
        listen_only=args.listen_only,
        fsync=not args.no_fsync,
        inject_uj=args.inject or 0,
        stop_on_intrusion=args.on_intrusion == "stop",
        return_hold_us=None if key is not None else args.return_hold,
        bus_names=names,
    )
    if buses:
        return _run_buses(args, buses, core, config, key)
    codec = Codec(args.id_base)
    filters = codec.supervisor_watch_filters()
    if args.canopen or args.cia402:
        from canergy.live.shared_bus import STANDARD_FRAMES

        filters.append(STANDARD_FRAMES)  # CANopen's 11-bit ids
    bus = open_bus(args, filters)
    control = None
    manager = None
    network = None
    guarded = None
    try:
        # the socket first: a run that cannot bind it stops before the state file is written
        control = ControlServer(args.control) if args.control is not None else None
        service = SupervisorService(core, config, monotonic_us())
        _announce(args, service)
        manager, reader = _canopen(args, bus, service) if args.canopen else (None, None)
        handler: Any = service
        if args.cia402:
            from canergy.live.shared_bus import shared_network

            if manager is not None:
                network = manager.network
            else:
                network, reader = shared_network(bus)
            now = monotonic_us()
            guarded = guard_drives(args, network, bus, service, _timing(args), now, monotonic_us)
            handler = guarded
        runtime = BusRuntime(
            bus,
            handler,
            codec=codec,
            receives=Direction.TO_SUPERVISOR,
            listen_only=args.listen_only,
            source=reader,
            auth=_auth(args, key, codec, service.freshness),
        )
        service.bus_counters = runtime.counters
        _serve(runtime, service, control, manager=manager)
        return _exit_status(service)
    finally:
        if control is not None:
            control.close()
        if guarded is not None:
            guarded.halt_all(monotonic_us())  # an exit never leaves a drive running
            guarded.close()
        for net in {id(n): n for n in (network, manager and manager.network) if n}.values():
            net.notifier.stop()
        bus.shutdown()


def _run_buses(
    args: argparse.Namespace,
    specs: tuple[BusSpec, ...],
    core: Supervisor,
    config: ServiceConfig,
    key: Any,
) -> int:
    """``--bus``: one service over every bus, a runtime per bus, one loop for them all."""
    codec = Codec(args.id_base)
    opened: list[Any] = []
    control = None
    group = None
    try:
        for spec in specs:
            filters = codec.supervisor_watch_filters()
            opened.append(open_bus_at(args, spec.interface, spec.channel, filters, spec.name))
        # the socket first: a run that cannot bind it stops before the state file is written
        control = ControlServer(args.control) if args.control is not None else None
        service = SupervisorService(core, config, monotonic_us())
        _announce(args, service)
        router = BusRouter()
        for i, (spec, bus) in enumerate(zip(specs, opened, strict=True)):
            port = BusPort(service, i, router, deadlines=i == 0)
            runtime = BusRuntime(
                bus,
                port,
                codec=codec,
                receives=Direction.TO_SUPERVISOR,
                listen_only=args.listen_only,
                auth=_auth(args, key, codec, port.freshness),
            )
            router.runtimes.append(runtime)
            service.buses[spec.name] = runtime.counters
        group = BusGroup(router.runtimes)
        _serve(group, service, control)
        return _exit_status(service)
    finally:
        if group is not None:
            group.close()
        if control is not None:
            control.close()
        for bus in opened:
            bus.shutdown()


def run_grant(args: argparse.Namespace) -> int:
    if args.control is not None:
        payload = {"grant": {"node": args.node, "amount_uj": args.amount}}
        try:
            answer = request(args.control, payload, args.timeout / US_PER_S)
        except (OSError, ValueError) as exc:
            print(
                f"canergy grant: cannot reach the supervisor at {args.control}: {exc}",
                file=sys.stderr,
            )
            return 2
        return _report_grant(answer)
    if isinstance(args.node, str):
        raise ValueError(
            f"--node {args.node}: a node named by its bus is granted through a running "
            "supervisor (--control)"
        )
    _check_widths(args)
    _check_state(args)
    key = _auth_key(args)
    nodes = tuple(sorted({args.node, *books_nodes(args.state)}))  # every node's books kept
    core = _build(args, nodes, key=key)
    config = ServiceConfig(
        limits=_limits(args),
        state_path=args.state,
        stop_timeout_us=args.stop_timeout,
        status_period_us=10**12,
        fsync=not args.no_fsync,
    )
    codec = Codec(args.id_base)
    bus = open_bus(args, codec.supervisor_watch_filters())
    answers: list[dict[str, Any]] = []
    deadline = monotonic_us() + args.timeout
    try:
        service = SupervisorService(core, config, monotonic_us())
        runtime = BusRuntime(
            bus,
            service,
            codec=codec,
            receives=Direction.TO_SUPERVISOR,
            auth=_auth(args, key, codec, service.freshness),
        )
        service.request_grant(args.node, args.amount, answers.append)
        _serve(runtime, service, None, until=lambda: bool(answers) or monotonic_us() > deadline)
    finally:
        bus.shutdown()
    if not answers:
        answers.append({"node": args.node, "error": "no answer before --timeout"})
    return _report_grant(answers[0])


def _report_grant(answer: dict[str, Any]) -> int:
    print(json.dumps(answer, sort_keys=True))
    return 0 if answer.get("outcome") == "COMMITTED" else 1


COMMANDS = {"supervisor": run_supervisor, "grant": run_grant}
