"""The ``canergy`` command line."""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from canergy import (
    __version__,
    cli_bench,
    cli_gateway,
    cli_inspect,
    cli_keys,
    cli_ledger,
    cli_live,
    cli_monitor,
    cli_plot,
    cli_sim,
)
from canergy.cli_args import (
    COUNT_MAX,
    bounded_int,
    duration,
    energy,
    id_base,
    node_ids,
    probability,
    seed,
)
from canergy.core.variants import VARIANTS
from canergy.extras import MissingExtra, require
from canergy.messages import MAX_NODE
from canergy.units import UJ_PER_J, US_PER_S

DEMO_TRANSACTIONS_MAX = 1_000_000
"""About a quarter of an hour of demo (some 1,000 transactions a second)."""
CHECK_BOUND_MAX = 10
"""Largest bound of the model checker's counters: the state space grows exponentially in each,
and three transactions already take minutes, so anything above is never explored to the end."""


def _demo_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "demo",
        help="supervisor and clients on python-can's virtual bus under injected faults",
        description=(
            "Run a supervisor and several clients on python-can's virtual bus, in virtual time, "
            "through a seeded fault injector; print the per-node and total ledger and a verdict. "
            "Exit status 0 when passive, 1 when energy was generated."
        ),
    )
    nodes = p.add_mutually_exclusive_group()
    nodes.add_argument(
        "--nodes",
        type=bounded_int(1, MAX_NODE),
        default=5,
        help="number of client nodes, ids 1..N (default 5)",
    )
    nodes.add_argument("--node-ids", type=node_ids, help="explicit node ids, e.g. 1-5,9")
    p.add_argument(
        "--transactions",
        type=bounded_int(1, DEMO_TRANSACTIONS_MAX),
        default=None,
        help=f"transactions to start in total (default 200, at most {DEMO_TRANSACTIONS_MAX:,})",
    )
    p.add_argument(
        "--duration",
        type=duration,
        metavar="TIME",
        help="virtual-time limit (default 300s; --topology tree: 60s of work, then the drain)",
    )
    p.add_argument(
        "--topology",
        choices=["bus", "tree"],
        default="bus",
        help="bus: one supervisor and --nodes clients; tree: a root supervisor, --gateways "
        "gateways on their own buses and --nodes nodes under each, faults on every bus",
    )
    p.add_argument(
        "--gateways",
        type=bounded_int(1, MAX_NODE),
        default=2,
        help="--topology tree: gateways under the root (default 2)",
    )
    p.add_argument(
        "--initial",
        type=energy,
        help="the (root) supervisor's initial usable budget (default 10J; --topology tree: 30J)",
    )
    p.add_argument("--variant", choices=sorted(VARIANTS), default="hardened")
    p.add_argument("--loss", type=probability, default=0.1, help="frame loss probability")
    p.add_argument(
        "--duplicate", type=probability, default=0.05, help="frame duplication probability"
    )
    p.add_argument(
        "--reorder",
        type=probability,
        default=0.05,
        help="probability a frame is held back behind later ones",
    )
    p.add_argument(
        "--corrupt",
        type=probability,
        default=0.01,
        help="probability one data bit flips in a frame",
    )
    p.add_argument(
        "--resets",
        type=bounded_int(0, 100),
        default=2,
        help="power losses of random nodes (or the supervisor) during the run; --topology tree: "
        "of gateways, and as many of nodes, and one of the root when above 0",
    )
    p.add_argument(
        "--commit-ratio",
        type=probability,
        default=0.8,
        help="probability the supervisor commits an acknowledged intention",
    )
    p.add_argument("--seed", type=seed, default=0, help="0..2**32-1 (default 0)")
    p.add_argument(
        "--log",
        type=Path,
        help="capture every frame on the bus (.log is candump -l; .asc, .blf, .csv, "
        ".trc as python-can writes them)",
    )
    p.add_argument("--json", action="store_true", help="print the result as JSON")


def _run_tree(args: argparse.Namespace) -> int:
    from canergy.demo.tree import TreeConfig, format_tree, run_tree
    from canergy.faults import FaultProfile

    given = [
        flag
        for flag, value in (
            ("--node-ids", args.node_ids),
            ("--transactions", args.transactions),
            ("--log", args.log),
        )
        if value is not None
    ]
    if given or args.variant != "hardened":
        raise ValueError(
            f"--topology tree: not with {', '.join(given) or '--variant'} (it runs the hardened "
            "rules, --nodes under each of --gateways, for --duration)"
        )
    cfg = TreeConfig(
        gateways=args.gateways,
        nodes=args.nodes,
        initial=TreeConfig().initial if args.initial is None else args.initial,
        duration_us=args.duration or TreeConfig().duration_us,
        faults=FaultProfile(
            loss=args.loss, duplicate=args.duplicate, reorder=args.reorder, corrupt=args.corrupt
        ),
        seed=args.seed,
        gateway_resets=args.resets,
        node_resets=args.resets,
        root_resets=min(args.resets, 1),
        commit_ratio=args.commit_ratio,
    )
    result = run_tree(cfg)
    print(json.dumps(result.as_json(), indent=2) if args.json else format_tree(result))
    return 0 if result.passive else 1


def _run_demo(args: argparse.Namespace) -> int:
    from canergy.demo import DemoConfig, format_report, run_demo
    from canergy.faults import FaultProfile

    if args.topology == "tree":
        return _run_tree(args)
    cfg = DemoConfig(
        nodes=args.node_ids or tuple(range(1, args.nodes + 1)),
        transactions=args.transactions or 200,
        duration_us=args.duration or 300 * US_PER_S,
        initial=10 * UJ_PER_J if args.initial is None else args.initial,
        variant=args.variant,
        faults=FaultProfile(
            loss=args.loss, duplicate=args.duplicate, reorder=args.reorder, corrupt=args.corrupt
        ),
        seed=args.seed,
        resets=args.resets,
        commit_ratio=args.commit_ratio,
        log=args.log,
    )
    result = run_demo(cfg)
    if args.json:
        print(json.dumps(result.as_json(), indent=2))
    else:
        print(format_report(result))
    return 0 if result.passive else 1


def _check_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from canergy.check.chain import BROKEN_RULES, ChainBounds
    from canergy.check.model import Bounds
    from canergy.check.workers import MAX_WORKERS

    d = Bounds()
    p = sub.add_parser(
        "check",
        help="exhaustively model-check the protocol core within bounds",
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
    count = bounded_int(0, CHECK_BOUND_MAX)
    positive = bounded_int(1, CHECK_BOUND_MAX)
    p.add_argument("--variant", choices=sorted(VARIANTS), default="hardened")
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
        f"{ChainBounds().in_flight} per leg)",
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
        action="store_true",
        help="report states, depth and rate on stderr every 100,000 states",
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
        type=bounded_int(1, MAX_WORKERS),
        default=None,
        help="processes: 2, one storing states while the other expands them (same result), "
        "or 1; default 2 when two cores are free to this process",
    )
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
        choices=BROKEN_RULES,
        help="--topology chain with a gateway rule broken on purpose, to see a counterexample: "
        "early-grant grants below what the intention above holds before its commit; "
        "split-save writes the two roles to two files, one after the other",
    )


_NOT_IN_CHAIN = (
    "engine",
    "workers",
    "nv_losses",
    "old_copies",
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
    if args.variant != "hardened" or given:
        flags = ", ".join("--" + name.replace("_", "-") for name in given) or "--variant"
        raise ValueError(f"--topology chain checks the hardened rules only; not with {flags}")
    bounds = ChainBounds(
        clients=args.clients,
        transactions=args.transactions,
        losses=args.losses,
        duplicates=args.duplicates,
        power_losses=args.power_losses,
        in_flight=args.in_flight or ChainBounds().in_flight,
        units=args.units,
        retries=args.retries,
    )
    result = check_chain(
        bounds=bounds,
        broken=args.broken_gateway,
        max_states=args.max_states,
        stop_at_first=not args.keep_going,
        progress=_report_progress if args.progress else None,
    )
    print(json.dumps(result.as_json(), indent=2) if args.json else format_chain(result, args.trace))
    return 1 if result.violations else 0


def _report_progress(states: int, depth: int, seconds: float) -> None:
    rate = states / seconds if seconds else 0.0
    print(f"  {states:,} states, depth {depth}, {seconds:.0f} s ({rate:,.0f}/s)", file=sys.stderr)


def _run_check(args: argparse.Namespace) -> int:
    from canergy.check import Bounds, check
    from canergy.check.report import format_summary, format_trace
    from canergy.check.workers import default_workers

    if args.topology == "chain":
        return _run_chain(args)
    if args.broken_gateway is not None:
        raise ValueError("--broken-gateway needs --topology chain")
    bounds = Bounds(
        clients=args.clients,
        transactions=args.transactions,
        losses=args.losses,
        duplicates=args.duplicates,
        power_losses=args.power_losses,
        nv_losses=args.nv_losses,
        old_copies=args.old_copies,
        forgeries=args.forgeries,
        replays=args.replays,
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
        progress=_report_progress if args.progress else None,
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


def _dbc_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("dbc", help="write the DBC describing canergy's frames")
    p.add_argument("-o", "--output", type=Path, help="file to write (default: stdout)")
    p.add_argument(
        "--auth",
        choices=["fd", "classic"],
        help="describe an authenticated layout: fd (CAN FD frames with FV and a 64-bit MAC) or "
        "classic (each message followed by a MAC frame)",
    )
    p.add_argument(
        "--id-base",
        type=id_base,
        default=None,
        help="29-bit identifier base, low 12 bits clear (default 0x0CE00000)",
    )


def _run_dbc(args: argparse.Namespace) -> int:
    from canergy.codec import DEFAULT_ID_BASE
    from canergy.dbc import dbc_text

    text = dbc_text(DEFAULT_ID_BASE if args.id_base is None else args.id_base, args.auth)
    if args.output:
        args.output.write_bytes(text.encode())
    else:
        sys.stdout.write(text)
    return 0


def _rules_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "rules",
        help="print the transition tables; --docs DIR also writes the reference and diagrams",
    )
    p.add_argument(
        "--docs",
        type=Path,
        metavar="DIR",
        help="write DIR/transitions.md and DIR/figures/states-*.png (the repo's: docs)",
    )


def _run_rules(args: argparse.Namespace) -> int:
    from canergy.rules_doc import markdown, write_docs

    if args.docs is None:
        sys.stdout.write(markdown())
        return 0
    require("plot")
    if not args.docs.is_dir():
        raise ValueError(f"--docs {args.docs}: not a directory")
    for path in write_docs(args.docs):
        print(f"wrote {path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="canergy",
        description="Passive energy budget transactions over CAN (Groothuis & Stramigioli).",
    )
    parser.add_argument("--version", action="version", version=f"canergy {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _demo_parser(sub)
    _check_parser(sub)
    _dbc_parser(sub)
    _rules_parser(sub)
    cli_live.add_parsers(sub)
    cli_gateway.add_parsers(sub)
    cli_ledger.add_parsers(sub)
    cli_sim.add_parsers(sub)
    cli_inspect.add_parsers(sub)
    cli_monitor.add_parsers(sub)
    cli_plot.add_parsers(sub)
    cli_keys.add_parsers(sub)
    cli_bench.add_parsers(sub)
    return parser


_COMMANDS = {
    "demo": _run_demo,
    "check": _run_check,
    "dbc": _run_dbc,
    "rules": _run_rules,
    **cli_live.COMMANDS,
    **cli_gateway.COMMANDS,
    **cli_ledger.COMMANDS,
    **cli_sim.COMMANDS,
    **cli_inspect.COMMANDS,
    **cli_monitor.COMMANDS,
    **cli_plot.COMMANDS,
    **cli_keys.COMMANDS,
    **cli_bench.COMMANDS,
}


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return _COMMANDS[args.command](args)
    except BrokenPipeError:  # e.g. `canergy demo | head`: stop quietly like other CLI tools
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except (ValueError, OSError, cli_live.BusOpenError) as exc:  # bad values, paths, buses
        print(f"canergy {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except MissingExtra as exc:  # e.g. canergy plot: needs matplotlib: pip install ...
        print(f"canergy {args.command}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
