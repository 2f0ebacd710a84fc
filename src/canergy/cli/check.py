"""``canergy check``: exhaustively model-check the protocol core within bounds."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from typing import Any

from canergy.argtypes import (
    COUNT_MAX,
    bounded_int,
)
from canergy.cli.summaries import SUMMARIES
from canergy.core.variants import VARIANTS

CHECK_BOUND_MAX = 10
"""Largest bound of the model checker's counters: the state space grows exponentially in each,
and three transactions already take minutes, so anything above is never explored to the end."""


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from canergy.check.chain import BROKEN_RULES, ChainBounds
    from canergy.check.model import Bounds
    from canergy.check.workers import MAX_WORKERS

    d = Bounds()
    p = sub.add_parser(
        "check",
        help=SUMMARIES["check"],
        description=(
            "Breadth-first exploration of one supervisor, K clients and the frames in flight "
            "under every interleaving of deliveries, losses, duplicates, timer expiries, "
            "power losses and an attacker's forged or replayed frames, checking the "
            "conservation ledger in every state (--topology chain: a root supervisor, a gateway "
            "and K nodes below it, the ledger of every level). Exit status 1 when "
            f"energy can be generated, 0 otherwise. Every bound is at most {CHECK_BOUND_MAX} "
            "(--clients at most 8): the state space grows exponentially in each."
        ),
    )
    p.add_argument("--variant", choices=sorted(VARIANTS), default="hardened")
    _bound_flags(p, d, ChainBounds().in_flight)
    _search_flags(p, MAX_WORKERS)
    _output_flags(p, BROKEN_RULES)
    p.set_defaults(run=run)


def _bound_flags(p: argparse.ArgumentParser, d: Any, chain_in_flight: int) -> None:
    """What may happen in a run: clients, transactions, faults, an attacker, the budget."""
    count = bounded_int(0, CHECK_BOUND_MAX)
    positive = bounded_int(1, CHECK_BOUND_MAX)
    p.add_argument("--clients", type=bounded_int(1, 8), default=d.clients)
    p.add_argument(
        "--transactions",
        type=count,
        default=d.transactions,
        help="transactions the supervisor may begin",
    )
    p.add_argument("--losses", type=count, default=d.losses, help="frames that may be lost")
    p.add_argument(
        "--duplicates", type=count, default=d.duplicates, help="frames that may be duplicated"
    )
    p.add_argument(
        "--power-losses",
        type=count,
        default=d.power_losses,
        help="power losses of any node or the supervisor",
    )
    p.add_argument(
        "--nv-losses",
        type=count,
        default=d.nv_losses,
        help="node starts with its NV record unreadable (both slots lost; default 0)",
    )
    p.add_argument(
        "--old-copies",
        type=count,
        default=d.old_copies,
        help="node starts from the record before its last write (NV replaced by an old copy; "
        "default 0)",
    )
    p.add_argument(
        "--backups",
        action="store_true",
        help="with --old-copies: the old copy is a backup taken at any earlier moment (a step "
        "of its own), not the record before the node's last write",
    )
    p.add_argument(
        "--supervisor-old-copies",
        type=count,
        default=d.supervisor_old_copies,
        help="supervisor starts from its state as it was before its last write (a backup put "
        "back; default 0)",
    )
    p.add_argument(
        "--supervisor-backups",
        action="store_true",
        help="with --supervisor-old-copies: the supervisor's old copy is a backup of its state "
        "taken at any earlier moment (a step of its own), not its state before its last write",
    )
    p.add_argument(
        "--resyncs",
        type=count,
        default=d.resyncs,
        help="--variant witnessed: re-syncs of one idle node by the supervisor (a SYNC with a "
        "fresh nonce, as when a begin is refused as beyond the window; default 0)",
    )
    p.add_argument(
        "--forgeries",
        type=count,
        default=d.forgeries,
        help="frames a keyless attacker builds and sends (the codec is public; default 0)",
    )
    p.add_argument(
        "--replays",
        type=count,
        default=d.replays,
        help="frames seen earlier on the bus that an attacker sends again, at any later time "
        "(what is left to it in the authenticated mode; default 0)",
    )
    p.add_argument(
        "--in-flight",
        type=positive,
        default=None,
        help=f"most frames in flight at once (default {d.in_flight}; --topology chain: "
        f"{chain_in_flight} per leg)",
    )
    p.add_argument(
        "--units",
        type=positive,
        default=d.units,
        help="initial budget in units (1 unit = 1 mJ); grants are 1..units",
    )
    p.add_argument("--retries", type=count, default=d.retries, help="N: re-sends before giving up")
    p.add_argument(
        "--timeouts",
        type=count,
        default=None,
        help="timer expiries allowed in one run (default: unbounded)",
    )
    p.add_argument("--no-returns", action="store_true", help="clients never return energy")
    p.add_argument("--no-spending", action="store_true", help="actuators never spend")


def _search_flags(p: argparse.ArgumentParser, max_workers: int) -> None:
    """How the search runs: its limits, reductions, engine and processes."""
    p.add_argument(
        "--max-states",
        type=bounded_int(1, COUNT_MAX),
        default=None,
        help="stop after this many states (the result is then incomplete)",
    )
    p.add_argument(
        "--continue",
        dest="keep_going",
        action="store_true",
        help="keep exploring after the first violation and count every violating "
        "state (default: stop at the first, which is a shortest one)",
    )
    p.add_argument(
        "--progress",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="report states, depth and rate on stderr every 100,000 states (default: when "
        "stderr is a terminal)",
    )
    p.add_argument(
        "--no-symmetry",
        action="store_true",
        help="store every node labeling separately (default: clients are interchangeable)",
    )
    p.add_argument(
        "--no-subsumption",
        action="store_true",
        help="also store states already reached with smaller run counters",
    )
    p.add_argument(
        "--engine",
        choices=["compact", "reference"],
        default=None,
        help="compact: worlds packed into ints, each node's moves worked out once (default); "
        "reference: the World-object search, slower, for cross-checks (same states, same trace)",
    )
    p.add_argument(
        "--workers",
        type=bounded_int(1, max_workers),
        default=None,
        help="processes: 2, one storing states while the other expands them (same result), "
        "or 1; default 2 when two cores are free to this process",
    )


def _output_flags(p: argparse.ArgumentParser, broken_rules: Any) -> None:
    """What is printed, and the topology (a chain, with a gateway rule broken on purpose)."""
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--trace", action="store_true", help="print the counterexample step by step")
    p.add_argument(
        "--topology",
        choices=["single", "chain"],
        default="single",
        help="single: one supervisor and --clients nodes; chain: a root supervisor, a gateway "
        "(client above, supervisor below) and --clients nodes below it, faults on both legs, "
        "--power-losses of any of them (--transactions per supervisor, --in-flight per leg)",
    )
    p.add_argument(
        "--broken-gateway",
        choices=broken_rules,
        help="--topology chain with a gateway rule broken on purpose, to see a counterexample: "
        "early-grant grants below what the intention above holds before its commit; "
        "split-save writes the two roles to two files, one after the other",
    )
    p.add_argument(
        "--gateway-old-copies",
        type=bounded_int(0, CHECK_BOUND_MAX),
        default=0,
        help="--topology chain: the gateway starts from its record before its last write (a "
        "backup put back; default 0); creates energy under --variant hardened, not witnessed",
    )


CHAIN_VARIANTS = ("hardened", "witnessed")
_NOT_IN_CHAIN = (
    "engine",
    "workers",
    "nv_losses",
    "old_copies",
    "backups",
    "supervisor_old_copies",
    "supervisor_backups",
    "resyncs",
    "forgeries",
    "replays",
    "timeouts",
    "no_returns",
    "no_spending",
    "no_symmetry",
    "no_subsumption",
)


def _run_chain(args: argparse.Namespace) -> int:
    from canergy.check.chain import ChainBounds, check_chain, format_chain

    given = [name for name in _NOT_IN_CHAIN if getattr(args, name)]
    if given:
        flags = ", ".join("--" + name.replace("_", "-") for name in given)
        raise ValueError(f"--topology chain: not with {flags}")
    if args.variant not in CHAIN_VARIANTS:
        raise ValueError(f"--topology chain checks the {' and '.join(CHAIN_VARIANTS)} rules")
    if args.broken_gateway is not None and args.variant != "hardened":
        raise ValueError("--broken-gateway breaks a rule of the hardened gateway")
    bounds = ChainBounds(
        clients=args.clients,
        transactions=args.transactions,
        losses=args.losses,
        duplicates=args.duplicates,
        power_losses=args.power_losses,
        in_flight=args.in_flight or ChainBounds().in_flight,
        units=args.units,
        retries=args.retries,
        old_copies=args.gateway_old_copies,
    )
    result = check_chain(
        args.variant,
        bounds=bounds,
        broken=args.broken_gateway,
        max_states=args.max_states,
        stop_at_first=not args.keep_going,
        progress=_progress(args),
    )
    print(json.dumps(result.as_json(), indent=2) if args.json else format_chain(result, args.trace))
    return 1 if result.violations else 0


def _progress(args: argparse.Namespace) -> Callable[[int, int, float], None] | None:
    """``--progress``, or by default progress on a terminal: a long check is never silent."""
    shown = sys.stderr.isatty() if args.progress is None else args.progress
    return _report_progress if shown else None


def _report_progress(states: int, depth: int, seconds: float) -> None:
    rate = states / seconds if seconds else 0.0
    print(f"  {states:,} states, depth {depth}, {seconds:.0f} s ({rate:,.0f}/s)", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    from canergy.check import Bounds, check
    from canergy.check.report import format_summary, format_trace
    from canergy.check.workers import default_workers

    if args.topology == "chain":
        return _run_chain(args)
    if args.broken_gateway is not None or args.gateway_old_copies:
        raise ValueError("--broken-gateway and --gateway-old-copies need --topology chain")
    if args.resyncs and not VARIANTS[args.variant].lifts_tx:
        raise ValueError(f"--resyncs: the {args.variant} rules have no re-sync")
    for backups, copies, flag, copies_flag in (
        (args.backups, args.old_copies, "--backups", "--old-copies"),
        (
            args.supervisor_backups,
            args.supervisor_old_copies,
            "--supervisor-backups",
            "--supervisor-old-copies",
        ),
    ):  # a backup that can never come back checks nothing: refused, not ignored
        if backups and not copies:
            raise ValueError(f"{flag} needs {copies_flag} 1 or more (a copy that can come back)")
    bounds = Bounds(
        clients=args.clients,
        transactions=args.transactions,
        losses=args.losses,
        duplicates=args.duplicates,
        power_losses=args.power_losses,
        nv_losses=args.nv_losses,
        old_copies=args.old_copies,
        backups=args.backups,
        supervisor_old_copies=args.supervisor_old_copies,
        supervisor_backups=args.supervisor_backups,
        forgeries=args.forgeries,
        replays=args.replays,
        resyncs=args.resyncs,
        in_flight=args.in_flight or Bounds().in_flight,
        units=args.units,
        retries=args.retries,
        timeouts=args.timeouts,
        returns=not args.no_returns,
        spending=not args.no_spending,
    )
    result = check(
        args.variant,
        bounds,
        max_states=args.max_states,
        stop_at_first=not args.keep_going,
        progress=_progress(args),
        symmetry=not args.no_symmetry,
        subsumption=not args.no_subsumption,
        engine=args.engine or "compact",
        workers=args.workers or (default_workers() if args.engine != "reference" else 1),
    )
    if args.json:
        print(json.dumps(result.as_json(), indent=2))
    else:
        print(format_summary(result))
        if args.trace:
            print(format_trace(result))
    return 1 if result.violations else 0
