"""``canergy bench``: every comparison in one process, or the live figures on a bus you name."""

from __future__ import annotations

import argparse
import json
import sys
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from canergy.argtypes import add_duration, bounded_int
from canergy.cli.shared.bus_flags import add_bus_flags
from canergy.cli.summaries import SUMMARIES
from canergy.live.atomic import check_writable_dir

if TYPE_CHECKING:
    from canergy.bench.on_bus import BusTarget


def node_counts(text: str) -> tuple[int, ...]:
    """``1,16``: how many nodes each row runs (1-127 each)."""
    parse = bounded_int(1, 127)
    return tuple(parse(part.strip()) for part in text.split(","))


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "bench",
        help=SUMMARIES["bench"],
        description="Without bus flags: every comparison in this process, the live stack on "
        "python-can's virtual bus. With bus flags (-i/-c...): the supervisor in this process on "
        "that bus, the nodes in another process (the registered client emulator, or "
        "--c-node), then python-canopen SDO writes to an SDO server process on the same bus.",
    )
    p.add_argument("--quick", action="store_true", help="smoke run: seconds, figures meaningless")
    p.add_argument("--json", type=Path, help="also write the results here")
    add_bus_flags(p)
    bus = p.add_argument_group("on a bus (any python-can interface but virtual)")
    bus.add_argument(
        "--nodes",
        type=node_counts,
        default=(1, 16),
        metavar="N[,N...]",
        help="one row per count of nodes (default 1,16)",
    )
    add_duration(bus, "--duration", 3_000_000, "measured time per row, after a warm-up")
    bus.add_argument(
        "--writes",
        type=bounded_int(1, 1_000_000),
        default=2_000,
        help="SDO writes of the baseline (default 2000)",
    )
    bus.add_argument(
        "--c-node",
        type=Path,
        help="run the nodes as this C node program (firmware/build/canergy-node), one process "
        "per node; SocketCAN only",
    )
    bus.add_argument(
        "--core",
        choices=("both", "python", "c"),
        default="both",
        help="the supervisor's core: both in turn (default; the Python core alone where the C "
        "core is not built), or one",
    )
    p.set_defaults(run=run)


def _cores(choice: str) -> tuple[str, ...]:
    """The supervisor cores ``--core`` names, in the order they run; a clear error when it
    names the C core and it is not built."""
    from canergy.ccore.supervisor import missing

    if choice == "python":
        return ("python",)
    why = missing()
    if choice == "c" and why:
        raise ValueError(f"--core c: {why}")
    if why:
        print(f"canergy bench: the Python core only: {why}", file=sys.stderr)
        return ("python",)
    return ("c",) if choice == "c" else ("python", "c")


def bus_target(args: argparse.Namespace) -> BusTarget:
    """The bus the flags name, for the bench's processes and this one."""
    from canergy.bench.on_bus import BusTarget
    from canergy.cli.shared.bus_flags import bus_argv, open_bus

    return BusTarget(
        tuple(bus_argv(args, id_base=False)),
        getattr(args, "interface", None),
        getattr(args, "channel", None),
        args.id_base,
        partial(open_bus, args),
    )


def run(args: argparse.Namespace) -> int:
    from canergy.bench.code import line
    from canergy.bench.run import c_core_lines, live_lines, run, table

    if args.json is not None:  # before minutes of measuring, not after
        check_writable_dir(args.json, "--json")
    results: dict[str, Any]
    if getattr(args, "interface", None) is None:
        results = run(quick=args.quick)
        for reason in results["skipped"]:
            print(f"canergy bench: {reason}", file=sys.stderr)
        print(table(results))
    else:
        from canergy.bench.on_bus import run_on_bus

        if args.c_node is not None and not args.c_node.is_file():
            raise FileNotFoundError(f"--c-node {args.c_node}: no such program")
        seconds = 0.5 if args.quick else args.duration / 1e6
        writes = 50 if args.quick else args.writes
        results = run_on_bus(
            bus_target(args), args.nodes, seconds, writes, args.c_node, _cores(args.core)
        )
        where = " ".join(
            str(getattr(args, n, None) or "") for n in ("interface", "channel")
        ).strip()
        print(f"live stack on {where}, nodes: {results['nodes_by']}; {line(results['code'])}")
        print("\n".join(live_lines(results) + c_core_lines(results)))
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return 0
