"""``canergy grant``: one grant, through a running supervisor (``--control``) or as a single run."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from canergy.argtypes import add_duration, bounded_int, grant_amount
from canergy.bus_keys import parse_node_id
from canergy.cli.shared.bus_flags import open_bus
from canergy.cli.shared.live import (
    auth_config,
    auth_key,
    check_state,
    check_widths,
    core_config,
    grant_limits,
    supervisor_flags,
)
from canergy.cli.summaries import SUMMARIES
from canergy.codec import Codec
from canergy.live.atomic import warn_no_fsync
from canergy.live.runtime import monotonic_us
from canergy.live.serve import serve_supervisor
from canergy.live.supervisor.build import SupervisorConfig, build_supervisor, open_core
from canergy.live.supervisor.control import MAX_STATUS, NoAnswer, NoSupervisor, request
from canergy.live.supervisor.service import ServiceConfig
from canergy.live.supervisor.state_file import books_nodes
from canergy.units import US_PER_S, format_energy

STATUS_WAIT_S = 5.0
"""How long ``grant`` waits for the status it asks for once its grant went unanswered."""


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    g = sub.add_parser(
        "grant",
        help=SUMMARIES["grant"],
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
    supervisor_flags(g)
    g.set_defaults(run=run)


def _grant_node(text: str) -> int | str:
    """``grant --node``: an id, or ``BUS/NODE`` (checked by the supervisor that has buses)."""
    bus, sep, node = text.rpartition("/")
    if not sep:
        return bounded_int(1, 127)(text)
    if not bus or parse_node_id(node) is None:
        raise argparse.ArgumentTypeError(f"{text[:40]!r}: expected a node id 1-127 or BUS/NODE")
    return text


def run(args: argparse.Namespace) -> int:
    if args.control is not None:
        payload = {"grant": {"node": args.node, "amount_uj": args.amount}}
        try:
            answer = request(args.control, payload, args.timeout / US_PER_S)
        except NoSupervisor as exc:
            print(
                f"canergy grant: {exc}: is `canergy supervisor --control {args.control}` "
                "running (as this user)?",
                file=sys.stderr,
            )
            return 2
        except NoAnswer:
            print(
                f"canergy grant: the supervisor at {args.control} took the request, but node "
                f"{args.node} took no grant within --timeout {args.timeout / US_PER_S:g} s (the "
                "request stays queued there until the node is heard or the supervisor stops): "
                f"{_node_state(args.control, args.node)}",
                file=sys.stderr,
            )
            return 1
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
    check_widths(args)
    check_state(args)
    key = auth_key(args)
    nodes = tuple(sorted({args.node, *books_nodes(args.state)}))  # every node's books kept
    config = _config(args, nodes, key)
    core = open_core(config)
    bus = open_bus(args, Codec(args.id_base).supervisor_watch_filters())
    answers: list[dict[str, Any]] = []
    deadline = monotonic_us() + args.timeout
    try:
        built = build_supervisor(config, [bus], core=core)
        service = built.service
        service.request_grant(args.node, args.amount, answers.append)
        warn_no_fsync("canergy grant", args.no_fsync)
        serve_supervisor(
            built.loop, service, None, until=lambda: bool(answers) or monotonic_us() > deadline
        )
    finally:
        bus.shutdown()
    if not answers:
        waiting = service.waiting()
        why = f" ({service.waiting_why(waiting)})" if waiting else ""
        answers.append({"node": args.node, "error": f"no answer before --timeout{why}"})
    return _report_grant(answers[0])


def _config(args: argparse.Namespace, nodes: tuple[int, ...], key: Any) -> SupervisorConfig:
    """The flags as the builder takes them: a supervisor for one grant, no status."""
    service = ServiceConfig(
        limits=grant_limits(args),
        state_path=args.state,
        stop_timeout_us=args.stop_timeout,
        status_period_us=10**12,
        fsync=not args.no_fsync,
    )
    return SupervisorConfig(
        core=core_config(args, nodes),
        service=service,
        id_base=args.id_base,
        auth=auth_config(args, key),
    )


def _node_state(control: Path, node: int | str) -> str:
    """What the supervisor's status says of ``node`` (and of its bus when nothing is heard)."""
    try:
        status = request(control, {"status": True}, STATUS_WAIT_S, max_answer=MAX_STATUS)
    except (OSError, ValueError) as exc:
        return f"its status did not come either ({exc})"
    info = status.get("nodes", {}).get(str(node))
    if not isinstance(info, dict):
        return "the supervisor's status does not show it"
    received = status.get("frames_received")
    if info.get("lost"):
        text = f"the supervisor has heard nothing from node {node} lately: it is lost"
        text += f" (frames received from the bus in all: {received})"
    elif info.get("level_uj") is None:
        text = f"node {node} is heard but has not reported its level yet"
    else:
        text = f"node {node} reports {format_energy(info['level_uj'])}"
    text += f"; its transaction state is {info.get('state')}"
    if status.get("bus_note"):
        text += f"; on its bus, {status['bus_note']}"
    return text


def _report_grant(answer: dict[str, Any]) -> int:
    print(json.dumps(answer, sort_keys=True))
    return 0 if answer.get("outcome") == "COMMITTED" else 1
