"""``canergy demo``: supervisor and clients on python-can's virtual bus under injected
faults."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from canergy.argtypes import (
    bounded_int,
    duration,
    energy,
    node_ids,
    probability,
    seed,
)
from canergy.cli.summaries import SUMMARIES
from canergy.core.variants import RUNNABLE
from canergy.messages import MAX_NODE
from canergy.units import UJ_PER_J, US_PER_S

DEMO_TRANSACTIONS_MAX = 1_000_000
"""About a quarter of an hour of demo (some 1,000 transactions a second)."""


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "demo",
        help=SUMMARIES["demo"],
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
    p.add_argument("--variant", choices=sorted(RUNNABLE), default="hardened")
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
    p.set_defaults(run=run)


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


def run(args: argparse.Namespace) -> int:
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
