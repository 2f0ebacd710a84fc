"""``python -m firmware_model``: emulated actuator nodes on any python-can bus.

Exit status: 0 after SIGINT/SIGTERM (final status written), 2 for bad arguments or a bus that
cannot be opened, 3 after a simulated power loss (``--crash-after`` or SIGUSR1).
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import signal
import sys
from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import Any

import can

from canergy.argtypes import COUNT_MAX, add_duration, bounded_int, energy, node_ids, power
from canergy.auth.frames import FrameAuth, Layout
from canergy.auth.keys import load_key
from canergy.cli.shared.bus_flags import add_bus_flags, open_bus
from canergy.codec import Codec
from canergy.core import Timing
from canergy.errors import BusOpenError
from canergy.live.atomic import (
    check_private_dir,
    check_writable_dir,
    kept_by,
    same_file,
    warn_no_fsync,
    write_json_atomic,
)
from canergy.live.canopen.shared_bus import STANDARD_FRAMES, SharedReader, shared_network
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.live.serve import serve
from canergy.messages import Direction
from firmware_model.actuator import PowerProfile
from firmware_model.canopen_node import CanopenFace
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NV_FILE_SIZES, NvError, NvSeal, NvStore, SimulatedPowerLoss

EXIT_POWER_LOSS = 3


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m firmware_model",
        description="Emulate canergy client nodes (actuators with an energy budget) on a CAN bus.",
    )
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--node", type=bounded_int(1, 127), help="one node id")
    which.add_argument("--nodes", type=node_ids, help="several node ids in one process: 1-20,33")
    add_bus_flags(p)
    p.add_argument(
        "--nv",
        type=Path,
        required=True,
        help="NV store: a file for --node, a directory (node-<id>.nv inside) for --nodes",
    )
    p.add_argument("--no-fsync", action="store_true", help="skip fsync of NV writes (tests)")
    drive = p.add_mutually_exclusive_group()
    drive.add_argument("--power", type=power, default=0, help="constant draw, e.g. 0.5W")
    drive.add_argument("--power-profile", type=Path, help="CSV of time_s,watts rows, repeated")
    add_duration(p, "--tick", 100_000, "actuator period")
    add_duration(p, "--telemetry-period", 1_000_000, "time between TELEMETRY frames")
    p.add_argument("--low-water", type=energy, default=0, help="report at once below this")
    p.add_argument("--return-above", type=energy, help="give back energy above this level")
    add_duration(p, "--response-timeout", 100_000, "wait this long for a reply")
    p.add_argument(
        "--variant",
        choices=("hardened", "witnessed"),
        default="hardened",
        help="the rules, as the supervisor's --variant; witnessed: the actuator runs only on "
        "draws the supervisor acknowledged, and every start waits for it to confirm the record",
    )
    p.add_argument(
        "--draw-chunk",
        type=energy,
        help="witnessed: energy drawn ahead of need (default: two ticks at peak power)",
    )
    p.add_argument(
        "--crash-after",
        type=bounded_int(1, COUNT_MAX),
        help="lose power during the N-th NV write of a node (torn slot), exit 3",
    )
    p.add_argument("--status-file", type=Path, help="JSON status, rewritten atomically")
    add_duration(p, "--status-period", 1_000_000, "time between status file writes")
    p.add_argument(
        "--auth",
        type=Path,
        metavar="KEY",
        help="authenticated mode: the node's key file (`canergy keys node`, mode 0600); with "
        "--nodes a directory of node-NNN.key files; --fd: CAN FD frames with a 64-bit MAC",
    )
    p.add_argument(
        "--canopen",
        action="store_true",
        help="also be CANopen slaves (canergy_node.eds): boot-up, heartbeat, NMT, SDO objects",
    )
    return p


def _nv_path(args: argparse.Namespace, node: int, several: bool) -> Path:
    if not several:
        return Path(args.nv)
    # 0755 whatever the umask (a 002 umask would make it group-writable: refused as not private
    # at the next start); the folders above it are the user's
    Path(args.nv).mkdir(mode=0o755, parents=True, exist_ok=True)
    return Path(args.nv) / f"node-{node:03d}.nv"


def _config(args: argparse.Namespace) -> NodeConfig:
    profile = (
        PowerProfile.from_csv(args.power_profile)
        if args.power_profile is not None
        else PowerProfile.constant(args.power / 1e6)
    )
    timeout = args.response_timeout
    return NodeConfig(
        power=profile,
        tick_us=args.tick,
        telemetry_period_us=args.telemetry_period,
        low_water=args.low_water,
        return_above=args.return_above,
        variant=args.variant,
        draw_chunk=args.draw_chunk,
        timing=Timing(
            response_timeout_us=timeout,
            command_timeout_us=2 * timeout,
            return_retry_us=2 * timeout,
        ),
    )


def status(host: NodeHost, runtime: BusRuntime, fsync: bool = True) -> dict[str, Any]:
    """The nodes' status and the bus's counters; ``fsync``: False under ``--no-fsync``."""
    nodes = [n.status() for n in host.nodes.values()]
    bus = {**runtime.counters.as_json(), "fsync": fsync}
    if len(nodes) == 1:
        return {**nodes[0], **bus}  # the bus's decode errors cover the node's and foreign ids
    return {"nodes": {str(n["node"]): n for n in nodes}, **bus}


class _Signals:
    """SIGINT and SIGTERM ask for a clean stop; SIGUSR1 simulates a power loss."""

    def __init__(self) -> None:
        self.stop = False
        signal.signal(signal.SIGINT, self._on_stop)
        signal.signal(signal.SIGTERM, self._on_stop)
        signal.signal(signal.SIGUSR1, self._lose_power)

    def request_stop(self, now: int = 0) -> None:
        self.stop = True

    def _on_stop(self, signum: int, frame: object) -> None:
        self.request_stop()

    @staticmethod
    def _lose_power(signum: int, frame: object) -> None:
        raise SimulatedPowerLoss("SIGUSR1")


def _host(args: argparse.Namespace, ids: tuple[int, ...]) -> NodeHost:
    """The nodes, each restored from its NV store."""
    config = _config(args)
    now = monotonic_us()
    several = len(ids) > 1 or args.nodes is not None
    return NodeHost([FirmwareNode(n, _nv_store(args, n, several), config, now) for n in ids])


def _nv_store(args: argparse.Namespace, node: int, several: bool) -> NvStore:
    path = _nv_path(args, node, several)
    keys: dict[int, bytes] | None = getattr(args, "node_keys", None)
    seal = None if keys is None else NvSeal(keys[node], node)  # --auth: the record sealed
    fsync, crash_after = not args.no_fsync, args.crash_after
    # one keeper per record: a second process on this file would spend it again
    store = partial(NvStore, path, node, fsync=fsync, crash_after=crash_after, seal=seal)
    return kept_by(path, "NV record", store, in_place=True)


def _check_nv_file(path: Path) -> None:
    """An existing --nv file must have an NV store's size (damaged slots are fine: the node then
    joins); any other file would be overwritten by the first record."""
    if path.is_file() and path.stat().st_size not in NV_FILE_SIZES:
        raise ValueError(
            f"--nv {path}: {path.stat().st_size} bytes is not an NV file of canergy "
            f"(0, {' or '.join(map(str, NV_FILE_SIZES[1:]))} bytes); give a new path"
        )


def _check_paths(args: argparse.Namespace, ids: tuple[int, ...]) -> None:
    """Before anything is read or written: every file the run writes can be written, no two
    options name one file (the NV records, the status and the power profile would overwrite each
    other), and no one but root and this user can replace an NV record or a key
    (``check_private_dir``)."""
    several = len(ids) > 1 or args.nodes is not None
    nv = Path(args.nv)
    if several and nv.exists() and not nv.is_dir():
        raise NotADirectoryError(
            f"--nv {nv}: not a directory (with --nodes, --nv holds one file per node)"
        )
    records = [nv / f"node-{n:03d}.nv" for n in ids] if several else [nv]
    made = several and not nv.exists()  # the --nodes directory, made at start in its parent
    for path in [nv] if made else records:
        check_writable_dir(path, "--nv")
        check_private_dir(path, "--nv")  # whoever can write its folder can roll a record back
    files = [("--nv", path) for path in ([nv, *records] if several else records)]
    if args.status_file is not None:
        check_writable_dir(args.status_file, "--status-file")
        files.append(("--status-file", args.status_file))
    if args.power_profile is not None:
        if not args.power_profile.is_file():
            raise FileNotFoundError(f"--power-profile {args.power_profile}: no such file")
        files.append(("--power-profile", args.power_profile))
    if args.auth is not None:  # a key read at start, then written over: lost
        keys = [args.auth / f"node-{n:03d}.key" for n in ids] if several else [args.auth]
        files += [("--auth", key) for key in keys]
        check_private_dir(keys[0], "--auth")
    for i, (option, path) in enumerate(files):
        for other, other_path in files[:i]:
            if option != other and same_file(path, other_path):
                raise ValueError(
                    f"{other} {other_path} and {option} {path} name the same file; "
                    "give each its own path"
                )
    for path in records:
        _check_nv_file(path)


def _start(args: argparse.Namespace, ids: tuple[int, ...]) -> tuple[NodeHost, Codec, can.BusABC]:
    """Check every path, open the bus, restore the nodes (errors: exit 2). The bus comes first:
    a bus that cannot be opened leaves no NV directory behind."""
    _check_paths(args, ids)
    args.node_keys = _node_keys(args, ids)
    codec = Codec(args.id_base)
    bus = _open(args, ids, codec)
    try:
        host = _host(args, ids)
    except BaseException:
        bus.shutdown()
        raise
    return host, codec, bus


def _node_keys(args: argparse.Namespace, ids: tuple[int, ...]) -> dict[int, bytes] | None:
    """``--auth``: each node's own key (a node key file per node; never the master)."""
    if args.auth is None:
        return None
    paths = (
        {ids[0]: args.auth}
        if args.node is not None
        else {n: Path(args.auth) / f"node-{n:03d}.key" for n in ids}
    )
    keys: dict[int, bytes] = {}
    for node, path in paths.items():
        key = load_key(path)
        if key.kind != "node":
            raise ValueError(f"--auth {path}: a node takes its own node key, not the master key")
        keys[node] = key.node_key(node)  # refuses another node's key
    return keys


def _auth(args: argparse.Namespace, codec: Codec, host: NodeHost) -> FrameAuth | None:
    if args.node_keys is None:
        return None
    layout = Layout.FD if getattr(args, "fd", False) else Layout.CLASSIC
    keys: dict[int, bytes] = args.node_keys
    auth = FrameAuth(codec, layout, keys.__getitem__, Direction.TO_CLIENT, host.freshness)
    bind_starts(auth, host)
    return auth


def bind_starts(auth: FrameAuth, host: NodeHost) -> None:
    """A 32-bit freshness for each node's JOIN (or, witnessed rules, RESUME): 16 random bits
    above its nonce, which the ADMIT's MAC binds."""
    for n, node in host.nodes.items():
        if node.joining:
            auth.join_fv[n] = secrets.randbits(16) << 16 | node.client.state.nonce
        elif node.resuming:
            auth.resume_fv[n] = secrets.randbits(16) << 16 | node.client.state.nonce


def _open(args: argparse.Namespace, ids: tuple[int, ...], codec: Codec) -> can.BusABC:
    """The bus, filtered to the nodes' frames (and CANopen's 11-bit ones with ``--canopen``)."""
    filters: list[dict[str, Any]] = [f for n in ids for f in codec.client_watch_filters(n)]
    if args.canopen:
        filters.append(STANDARD_FRAMES)
    return open_bus(args, filters)


def _canopen(bus: can.BusABC, host: NodeHost) -> tuple[SharedReader, can.Notifier | None]:
    """Boot every node as a CANopen slave; return canergy's reader and the shared Notifier."""
    network, reader = shared_network(bus)
    for fw in host.nodes.values():
        CanopenFace(fw, network).boot()
    return reader, network.notifier


def _serve(
    args: argparse.Namespace, host: NodeHost, runtime: BusRuntime, signals: _Signals
) -> None:
    """Run the bus loop until a stop is asked for, rewriting ``--status-file`` periodically."""
    next_status = [0]

    def each(now: int) -> None:
        if args.status_file is not None and now >= next_status[0]:
            write_json_atomic(
                args.status_file, status(host, runtime, not args.no_fsync), fsync=False
            )
            next_status[0] = now + args.status_period

    serve(runtime, lambda now: signals.stop, signals.request_stop, each)


def _close(bus: can.BusABC, notifier: can.Notifier | None) -> None:
    if notifier is not None:
        bus.stop_all_periodic_tasks()  # heartbeats
        notifier.stop()
    bus.shutdown()


def _report(args: argparse.Namespace, host: NodeHost, runtime: BusRuntime) -> None:
    final = status(host, runtime, not args.no_fsync)
    if args.status_file is not None:
        write_json_atomic(args.status_file, final, fsync=False)
    else:
        print(json.dumps(final, sort_keys=True))


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    ids = (args.node,) if args.node is not None else args.nodes
    signals = _Signals()  # first thing: a stop request during start-up must still end cleanly
    try:
        host, codec, bus = _start(args, ids)
    except (ValueError, OSError, BusOpenError) as exc:  # NvError is a ValueError
        parser.exit(2, f"{parser.prog}: error: {exc}\n")
    warn_no_fsync(parser.prog, args.no_fsync)
    reader, notifier = _canopen(bus, host) if args.canopen else (None, None)
    runtime = BusRuntime(
        bus,
        host,
        codec=codec,
        receives=Direction.TO_CLIENT,
        source=reader,
        auth=_auth(args, codec, host),
    )
    try:
        _serve(args, host, runtime, signals)
    except SimulatedPowerLoss as exc:
        print(f"firmware_model: simulated power loss: {exc}", file=sys.stderr)
        os._exit(EXIT_POWER_LOSS)  # no clean-up: the NV file is all that survives
    except NvError as exc:
        print(f"firmware_model: NV store: {exc}", file=sys.stderr)
        return 1
    finally:
        _close(bus, notifier)
    _report(args, host, runtime)
    return 0


if __name__ == "__main__":
    sys.exit(main())
