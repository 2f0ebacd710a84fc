"""``canergy ledger``: the conservation ledger of a tree, from its processes' status files.

The files must show one moment: taken from a stopped tree (each process writes its status at
exit), or they may disagree by what was in flight between two writes.

Each ``--level SUPERVISOR CLIENT...`` names one bus: the status file of its supervisor (``canergy
supervisor`` or the downstream side of ``canergy gateway``) and those of its clients (node
emulators, C nodes, or gateways, whose ``upstream`` part is their client record). Every gateway
named as a supervisor adds its link between its two roles. Exit 1 when any level created energy.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from canergy.cli.summaries import SUMMARIES
from canergy.ledger import Ledger, TreeLedger, ledger_from_status
from canergy.units import format_energy


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "ledger",
        help=SUMMARIES["ledger"],
        description="Close the books over one bus or a tree: for each --level give the status "
        "file of its supervisor (or gateway) and of its clients (a gateway's status file counts "
        "as a client of the level above). Exit status 0 when no level and no gateway created "
        "energy, 1 otherwise.",
    )
    p.add_argument(
        "--level",
        nargs="+",
        action="append",
        required=True,
        type=Path,
        metavar=("SUPERVISOR", "CLIENT"),
        help="a supervisor's status file, then its clients' (repeat for every bus); for a "
        "supervisor over several buses (--bus), each client as BUS=FILE",
    )
    p.add_argument("--json", action="store_true", help="print the ledger as JSON")
    p.set_defaults(run=run)


def _read(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a readable status file ({exc})") from exc
    if not isinstance(data, dict):
        raise ValueError(f"{path}: not a status file (a JSON object)")
    return data


def _client(path: Path, status: dict[str, Any]) -> list[dict[str, Any]]:
    """The client records of a status file: a node's, each node's of an emulator serving
    several (``nodes``), or a gateway's upstream part."""
    found: list[object]
    if status.get("role") == "gateway":
        found = [status.get("upstream")]
    elif "credited_uj" not in status and isinstance(status.get("nodes"), dict):
        found = list(status["nodes"].values())  # a node emulator serving several
    else:
        found = [status]
    records = [r for r in found if isinstance(r, dict) and "credited_uj" in r]
    if len(records) != len(found):
        raise ValueError(
            f"{path}: not a client's status (no credited_uj): give node status files "
            "(a node's or node emulator's --status-file) or a gateway's"
        )
    return records


def _clients(paths: list[Path]) -> list[dict[str, Any]] | dict[str, list[dict[str, Any]]]:
    """The clients' records; ``BUS=FILE`` names the bus of a supervisor over several buses."""
    plain: list[dict[str, Any]] = []
    by_bus: dict[str, list[dict[str, Any]]] = {}
    for given in paths:
        bus, eq, rest = str(given).partition("=")
        path = Path(rest) if eq and bus and "/" not in bus else given
        records = _client(path, _read(path))
        if path is given:
            plain.extend(records)
        else:
            by_bus.setdefault(bus, []).extend(records)
    if plain and by_bus:
        raise ValueError("give every client as BUS=FILE, or none")
    return by_bus or plain


def tree_from_files(levels: list[list[Path]]) -> TreeLedger:
    books: dict[str, Ledger] = {}
    gaps: dict[str, int] = {}
    for supervisor, *clients in levels:
        status = _read(supervisor)
        if "nodes" not in status or "initial_uj" not in status:
            raise ValueError(f"{supervisor}: not a supervisor's or gateway's status file")
        name = str(supervisor)
        try:
            books[name] = ledger_from_status(status, _clients(clients))
        except (KeyError, TypeError) as exc:
            raise ValueError(f"--level {supervisor}: a status file lacks {exc}") from None
        except ValueError as exc:  # clients that do not match the supervisor's nodes
            raise ValueError(f"--level {supervisor}: {exc}") from None
        if status.get("role") == "gateway":  # recomputed, not taken from the file's claim
            try:
                spent = int(status["upstream"]["spent_uj"])
                gaps[name] = int(status["injected_uj"]) - int(status["withdrawn_uj"]) - spent
            except (KeyError, TypeError, ValueError) as exc:
                raise ValueError(f"{supervisor}: a gateway's status file lacks {exc}") from None
    return TreeLedger(books, gaps)


def run(args: argparse.Namespace) -> int:
    try:
        tree = tree_from_files(args.level)
    except ValueError as exc:  # as a CLI error, naming the file
        print(f"canergy ledger: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(tree.as_json(), indent=2))
    else:
        for name, led in tree.levels.items():
            debt = (
                f" (drives' unpaid debt {format_energy(led.drive_debt)})" if led.drive_debt else ""
            )
            print(
                f"{name}: in {format_energy(led.initial + led.injected - led.withdrawn)}, held "
                f"{format_energy(led.held)}{debt}, dissipated {format_energy(led.dissipated)}"
            )
        for name, gap in tree.link_gaps.items():
            print(f"{name}: gateway link gap {gap} µJ")
        print(
            f"tree: dissipated {format_energy(tree.dissipated)}: "
            + ("PASSIVE" if tree.passive else "VIOLATION: energy created")
        )
    return 0 if tree.passive else 1
