"""``canergy inline``: MIT-mode motors guarded in line between two interfaces
(``canergy.live.devices.mit_forward``)."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from canergy.argtypes import add_duration, node_ids
from canergy.cli.shared.bus_flags import add_bus_flags, open_bus
from canergy.cli.shared.live import add_on_stuck_flag, check_on_stuck
from canergy.cli.shared.mit import add_gate_flags, guard_config, mit_motors
from canergy.cli.summaries import SUMMARIES
from canergy.codec import Codec
from canergy.live.atomic import check_writable_dir, write_json_atomic
from canergy.live.devices.mit_bus import MitBus, MitMotor
from canergy.live.devices.mit_forward import MitForwarder
from canergy.live.runtime import monotonic_us

APP = "app"


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "inline",
        help=SUMMARIES["inline"],
        description="Sit between an application's bus (--app-interface, --app-channel, ...) and "
        "the motors' bus (-i/-c, where canergy supervisor runs): every frame the application "
        "sends to a guarded MIT-mode motor is forwarded only while its budget lasts, clamped "
        "so that the worst-case torque stays under the cap (feed-forward torque, kp·Δp, kd·Δv, "
        "velocity), or refused; both are counted in the status. Each motor's budget is a proxy "
        "client of the supervisor, under the canergy node id --mit-nodes gives it (list it in "
        "the supervisor's --nodes). Other classic frames cross both ways unchanged. Stop with "
        "Ctrl-C (SIGINT) or SIGTERM: every guarded motor is told to exit motor mode.",
    )
    add_bus_flags(p)
    add_bus_flags(p, id_base_flag=False, prefix=APP)
    g = p.add_argument_group("MIT-mode motors")
    g.add_argument("--mit", type=node_ids, metavar="IDS", required=True, help="motor CAN ids")
    g.add_argument(
        "--mit-nodes",
        type=node_ids,
        metavar="IDS",
        required=True,
        help="the proxies' canergy node ids, one per motor, in the same order",
    )
    add_gate_flags(g, model_required=True)
    add_on_stuck_flag(g, "motor ({node}: its CAN id)")
    p.add_argument("--status-file", type=Path, help="the gates' status as JSON")
    add_duration(p, "--status-period", 1_000_000, "time between status lines (and files)")
    p.set_defaults(run=run)


def motors(args: argparse.Namespace) -> list[MitMotor]:
    """The motors the flags describe (``ValueError`` naming the flag)."""
    if len(args.mit) != len(args.mit_nodes):
        raise ValueError(f"--mit names {len(args.mit)} motors, --mit-nodes {len(args.mit_nodes)}")
    sides = [  # a flag not given is not in the namespace (python-can's configuration has it)
        (getattr(args, f"{p}interface", None), getattr(args, f"{p}channel", None))
        for p in ("", "app_")
    ]
    if sides[0] == sides[1] and sides[0][1] is not None:
        raise ValueError("-c and --app-channel name the same bus: give the application its own")
    check_on_stuck(args)
    return mit_motors(args, args.mit_nodes)


def status_line(status: dict[str, Any]) -> str:
    parts = [f"to motors {status['to_motors']}, to app {status['to_app']}"]
    for m, s in status["motors"].items():
        c = s["commands"]
        why = f"STUCK: {s['stuck']}" if s["stuck"] else s["stop_reason"] or "running"
        parts.append(
            f"motor {m}: {s['guard']} ({why}), forwarded "
            f"{c['forwarded']}, clamped {c['clamped']}, refused {c['refused']}, "
            f"{s['usable_uj'] / 1e6:.3f} J left"
        )
    return "canergy inline: " + "; ".join(parts)


def say(line: str) -> None:
    """A motor stopped, released or STUCK, and ``--on-stuck``'s runs: on stderr at once."""
    print(f"canergy inline: {line}", file=sys.stderr, flush=True)


def run(args: argparse.Namespace, stop: threading.Event | None = None) -> int:
    """Forward until SIGINT or SIGTERM (or ``stop``, for a caller that runs it in a thread)."""
    wanted = motors(args)
    if args.status_file is not None:
        check_writable_dir(args.status_file, "--status-file")
    stop = stop or threading.Event()

    def request_stop(signum: int, frame: object) -> None:
        stop.set()

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, request_stop)
        signal.signal(signal.SIGTERM, request_stop)
    app = open_bus(args, [], prefix=APP)
    guarded = None
    try:
        guarded = MitBus(
            open_bus(args, []),
            wanted,
            codec=Codec(args.id_base),
            guard_config=guard_config(args),
            on_stuck=args.on_stuck,
            report=say,
        )
        forwarder = MitForwarder(app, guarded)
        next_at = [monotonic_us()]

        def report() -> None:
            if monotonic_us() < next_at[0]:
                return
            next_at[0] = monotonic_us() + args.status_period
            status = forwarder.status()
            print(status_line(status), file=sys.stderr, flush=True)
            if args.status_file is not None:
                write_json_atomic(args.status_file, status, fsync=False)

        forwarder.run(stop.is_set, report)
    finally:
        if guarded is not None:
            guarded.shutdown()
        app.shutdown()
    return 0
