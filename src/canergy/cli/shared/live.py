"""Flag groups and set-up shared by ``supervisor``, ``grant`` and ``gateway``: the books,
limits and timing, the service, authenticated mode, the files a run writes."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from canergy.argtypes import add_duration, bounded_int, energy, node_ids, power
from canergy.ccore.supervisor import missing
from canergy.cli.shared.bus_flags import add_bus_flags
from canergy.core import Timing
from canergy.core.variants import RUNNABLE
from canergy.live.atomic import check_private_dir, check_writable_dir, same_file
from canergy.live.devices.on_stuck import parse_on_stuck
from canergy.live.supervisor.build import AuthConfig, CoreConfig
from canergy.live.supervisor.control import check_control_path
from canergy.live.supervisor.policy import Limits, level_room
from canergy.live.supervisor.state_file import ACCEPT_EDITED
from canergy.messages import AMOUNT_MAX_MJ, QUANTUM_UJ, USABLE_MAX_UJ
from canergy.units import UJ_PER_J, format_energy

LARGEST_GRANT = AMOUNT_MAX_MJ * QUANTUM_UJ
LIVE_VARIANTS = sorted({*RUNNABLE, "witnessed"})
"""The rules a live supervisor runs: the demo's, and ``witnessed`` (its nodes draw through
numbered DEBITs and confirm every start: the emulator's ``--variant witnessed``)."""


def joules(uj: int) -> str:
    return format_energy(uj).replace(" ", "")


ROOM = f"{joules(USABLE_MAX_UJ)} (what a node's record holds) minus --max-grant"


def supervisor_flags(p: argparse.ArgumentParser) -> None:
    add_bus_flags(p)
    p.add_argument(
        "--variant",
        choices=LIVE_VARIANTS,
        default="hardened",
        help="the rules (default hardened); witnessed: a record restored from an older copy "
        "(a node's or the --state file) creates nothing (its nodes must run them too)",
    )
    p.add_argument("--initial", type=energy, default=10 * UJ_PER_J, help="budget of a new state")
    p.add_argument(
        "--core",
        choices=("auto", "c", "python"),
        default="auto",
        help="the rules' implementation: c (firmware/'s supervisor role, compiled at install; "
        "the hardened or witnessed rules; over several buses one C supervisor per bus), "
        "python, or auto (default): c where it is built and takes the configuration, python "
        "otherwise; the status names the one running",
    )
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
    p.add_argument(
        "--retries",
        type=bounded_int(0, 100),
        default=3,
        help="re-sends of an unanswered intention or command, each after --response-timeout, "
        "before the transaction is written off (default 3: 200 ms with the default timeout; "
        "raise both for a slow or loaded host)",
    )
    p.add_argument(
        "--max-grant",
        type=energy,
        default=LARGEST_GRANT,
        help=f"largest grant per transaction (default and at most {joules(LARGEST_GRANT)}, what "
        "one frame carries)",
    )
    p.add_argument(
        "--max-node-level",
        type=energy,
        help=f"never lift a node's level above this; at most {ROOM}, room for a written-off "
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
        help=f"top each node up to this reported level; at most {ROOM} (see --max-node-level)",
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


def rule_timing(args: argparse.Namespace, response_timeout_us: int | None = None) -> Timing:
    """The rules' timing from ``--response-timeout`` (or ``response_timeout_us``) and
    ``--retries``: a node waits twice the response timeout for a command or a RETURN_ACK."""
    timeout = args.response_timeout if response_timeout_us is None else response_timeout_us
    return Timing(
        response_timeout_us=timeout,
        retries=args.retries,
        command_timeout_us=2 * timeout,
        return_retry_us=2 * timeout,
    )


def core_choice(args: argparse.Namespace) -> str:
    """``--core`` resolved: "c" or "python". ``--core c`` where the C core cannot run is an
    error that says why; ``auto`` then takes the Python core. On one bus or several
    (``--bus``): over several, one C supervisor per bus (``canergy.ccore.buses``)."""
    wanted = getattr(args, "core", "python")
    if wanted == "python":
        return "python"
    why = (
        "it runs the hardened and witnessed rules only (--variant)"
        if args.variant not in ("hardened", "witnessed")
        else missing()
    )
    if why is None:
        return "c"
    if wanted == "c":
        raise ValueError(f"--core c: {why}")
    return "python"


def core_config(args: argparse.Namespace, nodes: tuple[int, ...]) -> CoreConfig:
    """The core's flags as the builder takes them (``--core`` resolved, ``--start-without``
    checked); with ``--bus`` ``nodes`` are session keys (``canergy.bus_keys``)."""
    kind = core_choice(args)  # before the state file is touched
    without = start_without(args, nodes)

    def warn(message: str) -> None:
        print(f"canergy {args.command}: warning: {message}", file=sys.stderr)

    return CoreConfig(
        nodes=nodes,
        initial_uj=args.initial,
        variant=args.variant,
        timing=rule_timing(args),
        kind=kind,
        state_path=args.state,
        accept_edited=args.accept_edited_state,
        start_without=without,
        keep_books=not getattr(args, "listen_only", False),
        warn=warn,
    )


def auth_config(args: argparse.Namespace, key: Any) -> AuthConfig | None:
    """``--auth`` (and ``--fd``, the frame layout) as the builder takes it; None without."""
    if key is None:
        return None
    return AuthConfig(key, args.auth, bool(getattr(args, "fd", False)))


def start_without(args: argparse.Namespace, nodes: tuple[int, ...]) -> frozenset[int]:
    """``--start-without``'s nodes, checked before anything is read or written: only under
    ``--variant witnessed`` (the rules whose starts wait for books), and among ``nodes``."""
    without = frozenset(getattr(args, "start_without", None) or ())
    if without and args.variant != "witnessed":
        raise ValueError("--start-without: only under --variant witnessed")
    if stray := sorted(without - set(nodes)):
        raise ValueError(
            f"--start-without: node(s) {', '.join(map(str, stray))} are not nodes it supervises"
        )
    return without


def start_without_flag(p: argparse.ArgumentParser, also: str = "") -> None:
    """``--start-without``: nodes a witnessed start does not wait for (either core); ``also``:
    where else the budget goes (a gateway returns it upstream)."""
    p.add_argument(
        "--start-without",
        type=node_ids,
        metavar="NODES",
        help="--variant witnessed: grant after a start without waiting for these nodes' books "
        "(e.g. 3,7: nodes that are off for long); what their books say they hold is written "
        "off (status started_without, stderr). RISK: if the state file was put back to an "
        "older copy, such a node may hold energy the restored books count in the budget again "
        f"(up to all it received since the copy), and that is granted to the other nodes{also}",
    )


def grant_limits(args: argparse.Namespace) -> Limits:
    return Limits(
        max_grant=args.max_grant,
        max_node_level=args.max_node_level,
        max_total=args.max_total,
        rate_uj_per_s=args.rate,
    )


def auth_key(args: argparse.Namespace) -> Any:
    """``--auth``'s master key, checked before anything is written or opened."""
    if args.auth is None:
        return None
    from canergy.auth.keys import load_key

    key = load_key(args.auth)
    if key.kind != "master":
        raise ValueError(f"--auth {args.auth}: a supervisor needs the master key, not a node key")
    if args.variant not in ("hardened", "witnessed"):
        raise ValueError("--auth needs the hardened or witnessed rules (--variant)")
    return key


def check_state(args: argparse.Namespace, *, required: bool = True) -> None:
    """``--state`` is given (when ``required``); every file the run writes can be written, none
    is another under a second name (nor a key file it reads), ``--control`` replaces nothing but
    a stale socket, and no one but root and this user can replace the state or a key file
    (``check_private_dir``). Reads and writes nothing."""
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
    keys = [
        (option, path)
        for option, path in (
            ("--auth", getattr(args, "auth", None)),
            ("--upstream-auth", getattr(args, "upstream_auth", None)),
        )
        if path is not None
    ]
    files = [*outputs, *keys]  # a key file read at start, then written over, is lost
    for i, (option, path) in enumerate(files):
        for other, other_path in files[: min(i, len(outputs))]:
            if same_file(path, other_path):
                raise ValueError(
                    f"{option} {path} and {other} {other_path} name the same file; "
                    "give each its own path"
                )
    for option, path in outputs:
        check_writable_dir(path, option)
        if option == "--control":
            check_control_path(path, option)
    books = [("--state", args.state)] if args.state is not None else []
    for option, path in (*books, *keys):  # the books and the keys that seal them
        check_private_dir(path, option)


def check_widths(args: argparse.Namespace) -> None:
    """No configuration may plan a node above what its record holds (``USABLE_MAX_UJ``)."""
    if not QUANTUM_UJ <= args.max_grant <= LARGEST_GRANT:
        raise ValueError(
            f"--max-grant {joules(args.max_grant)} must be {joules(QUANTUM_UJ)} to "
            f"{joules(LARGEST_GRANT)}, what one frame carries"
        )
    room = level_room(args.max_grant)
    for option, value in (
        ("--target", getattr(args, "target", None)),
        ("--max-node-level", args.max_node_level),
    ):
        if value is not None and value > room:
            raise ValueError(
                f"{option} {joules(value)} is above {joules(room)}: a node's record holds at "
                f"most {joules(USABLE_MAX_UJ)}, and a written-off grant (--max-grant "
                f"{joules(args.max_grant)}) may be paid back on top"
            )


def add_on_stuck_flag(p: argparse.ArgumentParser | argparse._ArgumentGroup, devices: str) -> None:
    """``--on-stuck CMD`` (``supervisor``, ``inline``): free text, checked by ``check_on_stuck``."""
    p.add_argument(
        "--on-stuck",
        metavar="CMD",
        help="run CMD (split as a shell would, run without one; {node} and {profile} filled in, "
        f"CANERGY_STUCK_* in its environment) once each time a guarded {devices} becomes "
        "STUCK, e.g. a relay cutting its supply; not waited for",
    )


def check_on_stuck(args: argparse.Namespace) -> None:
    """``--on-stuck``'s command line, if given (``ValueError`` naming the flag)."""
    if args.on_stuck is None:
        return
    try:
        parse_on_stuck(args.on_stuck)
    except ValueError as exc:
        raise ValueError(f"--on-stuck: {exc}") from None
