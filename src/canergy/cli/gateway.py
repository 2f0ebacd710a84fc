"""``canergy gateway``: a client of the supervisor above, the supervisor of the bus below."""

from __future__ import annotations

import argparse
import hmac
import random
import secrets
import sys
from functools import partial
from pathlib import Path
from typing import Any

from canergy.argtypes import add_duration, bounded_int, energy, node_ids, probability, seed
from canergy.auth.frames import FrameAuth, Layout
from canergy.auth.keys import Key, KeyFileError, frame_auth_keys, load_key
from canergy.auth.state_key import state_seal
from canergy.ccore.supervisor import make_below
from canergy.cli.shared.bus_flags import add_bus_flags, open_bus
from canergy.cli.shared.live import (
    auth_config,
    book_flags,
    check_state,
    check_widths,
    core_choice,
    grant_limits,
    rule_timing,
    service_flags,
    start_without,
    start_without_flag,
)
from canergy.cli.summaries import SUMMARIES
from canergy.codec import Codec
from canergy.core.gateway import Gateway
from canergy.core.state import Phase
from canergy.faults import FaultInjector, FaultProfile
from canergy.live.atomic import kept_by, warn_no_fsync
from canergy.live.bus_group import BusGroup
from canergy.live.gateway.process import GatewayFiles, Uplink, UplinkConfig
from canergy.live.gateway.state import load_gateway
from canergy.live.runtime import BusCounters, BusRuntime, monotonic_us
from canergy.live.serve import serve_supervisor
from canergy.live.supervisor.build import ASK_IT, SupervisorConfig, build_supervisor
from canergy.live.supervisor.policy import TopUp
from canergy.live.supervisor.service import ServiceConfig
from canergy.live.supervisor.state_file import keep_books
from canergy.live.supervisor.witness import RETURN_HOLD_MIN_US
from canergy.messages import QUANTUM_UJ, Direction

UP = "upstream"


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "gateway",
        help=SUMMARIES["gateway"],
        description="Run a gateway: node --node on the upstream bus (--upstream-* flags, e.g. "
        "--upstream-interface zenoh), supervisor of --nodes on the downstream bus (-i/-c ...). "
        "Energy committed to it upstream becomes its downstream budget at once; what it holds "
        "above --return-above goes back upstream as numbered returns. One --state file keeps "
        "both roles. Authenticated mode, leg by leg: --upstream-auth (its node key from the "
        "supervisor above) and --auth (its own master key, for its nodes). SIGINT/SIGTERM stop it "
        "cleanly.",
    )
    p.add_argument("--node", type=bounded_int(1, 127), required=True, help="its id upstream")
    p.add_argument("--nodes", type=node_ids, required=True, help="downstream node ids, e.g. 1-40")
    p.add_argument(
        "--variant",
        choices=("hardened", "witnessed"),
        default="hardened",
        help="the rules below (default hardened); witnessed: its nodes draw through numbered "
        "DEBITs and every start of the gateway waits for their books (SYNC)",
    )
    p.add_argument(
        "--upstream-variant",
        choices=("hardened", "witnessed"),
        default="hardened",
        help="the rules above (default hardened; the supervisor above must run the same); "
        "witnessed: what is forwarded below is drawn through a numbered DEBIT the supervisor "
        "above acknowledges first, and every start waits, granting nothing below, until it "
        "confirms this gateway's record (one restored from an older copy creates nothing)",
    )
    p.add_argument(
        "--core",
        choices=("auto", "c", "python"),
        default="auto",
        help="the downstream supervisor role's implementation: c (firmware/'s supervisor role, "
        "compiled at install, and its frame path), python, or auto (default): c where it is "
        "built, python otherwise; the status names the one running. The upstream client role "
        "and the gateway's rules between the two are the same on either",
    )
    start_without_flag(p, " or returned upstream")
    add_bus_flags(p)
    add_bus_flags(p, prefix=UP)
    book_flags(p)
    service_flags(p)
    p.add_argument(
        "--return-above",
        type=energy,
        help="return the downstream usable budget above this upstream (default: keep it); keep "
        "it above the --target the supervisor above gives this gateway, or the two would pass "
        "the same energy back and forth",
    )
    add_duration(p, "--telemetry-period", 100_000, "time between level reports upstream")
    add_duration(
        p,
        "--upstream-response-timeout",
        50_000,
        "the response timeout of the supervisor above (the gateway waits twice that for a command)",
    )
    for kind in ("loss", "duplicate", "reorder"):
        p.add_argument(
            f"--upstream-{kind}",
            type=probability,
            default=0.0,
            help=f"tests and soak runs: {kind} this fraction of the frames sent upstream",
        )
    p.add_argument("--fault-seed", type=seed, default=0, help="seed of the upstream faults")
    p.add_argument(
        "--auth",
        type=Path,
        metavar="MASTER_KEY",
        help="downstream: authenticated mode with the gateway's own master key (`canergy keys -o "
        "gw.key`; its nodes' keys are derived from it, never the key of the supervisor above); "
        "it also seals --state. With --fd one CAN FD frame and a 64-bit MAC, otherwise each frame "
        "is followed by a MAC frame (40-bit MAC)",
    )
    p.add_argument(
        "--upstream-auth",
        type=Path,
        metavar="NODE_KEY",
        help="upstream: authenticated mode with this gateway's node key, derived from the master "
        "key of the supervisor above for --node (`canergy keys --master root.key --nodes NODE -o "
        "keys/`); --upstream-fd for the CAN FD layout",
    )
    add_duration(
        p,
        "--return-hold",
        500_000,
        "without --auth: credit a node's RETURN only once its own TELEMETRY confirms it and this "
        "long has passed with no report of frames in its name (a forged RETURN is refuted, "
        "never credited; shorter, the node could not refute one in time)",
        low_us=RETURN_HOLD_MIN_US,
    )
    p.set_defaults(run=run)


def _keys(args: argparse.Namespace) -> tuple[Key | None, Key | None]:
    """The keys of the two legs (``--upstream-auth``, ``--auth``), checked before anything is
    written or opened: upstream this gateway's own node key, downstream a master key of its
    own. Each refusal is one line naming the file, never the key."""
    up = down = None
    if args.upstream_auth is not None:
        up = _load(args.upstream_auth, "--upstream-auth")
        if up.kind != "node":
            raise ValueError(
                f"--upstream-auth {args.upstream_auth}: a master key; upstream the gateway is "
                f"node {args.node} of the supervisor above and takes its node key (canergy keys "
                f"--master ROOT.key --nodes {args.node} -o keys/)"
            )
        if up.node != args.node:
            raise ValueError(
                f"--upstream-auth {args.upstream_auth}: the key of node {up.node}, but this "
                f"gateway is node {args.node} upstream (--node)"
            )
    if args.auth is not None:
        down = _load(args.auth, "--auth")
        if down.kind != "master":
            raise ValueError(
                f"--auth {args.auth}: a node key; downstream the gateway is a supervisor and "
                "needs a master key of its own (canergy keys -o GATEWAY.key)"
            )
        if up is not None and hmac.compare_digest(down.node_key(args.node), up.secret):
            raise ValueError(
                f"--auth {args.auth}: the master key --upstream-auth {args.upstream_auth} was "
                "derived from (the supervisor above's): a gateway holding it could speak for "
                "every node above; give it a master key of its own (canergy keys -o GATEWAY.key)"
            )
    return up, down


def _load(path: Path, flag: str) -> Key:
    """``load_key``'s checks, its refusal naming the flag too."""
    try:
        return load_key(path)
    except KeyFileError as exc:
        raise KeyFileError(f"{flag} {exc}") from None


def _build(
    args: argparse.Namespace, key: Key | None = None, core: str = "python"
) -> tuple[Gateway, bool]:
    """The gateway core from its state file; True when there is no file (a new gateway).
    ``key``: the downstream master key (``--auth``), which seals the state file; ``core``:
    its supervisor role's ("c" or "python", ``--core`` resolved). The state file's lock is
    held as long as the gateway lives (``kept_by``)."""
    fresh = not args.state.exists()  # read under the lock: nobody else writes it meanwhile
    made = partial(_from_books, args, key, core)
    return kept_by(args.state, "state file", made, hint=ASK_IT), fresh


def _from_books(args: argparse.Namespace, key: Key | None, core: str) -> Gateway:
    nodes = tuple(args.nodes)
    state = None
    seal = None if key is None else state_seal(key, args.node)
    if args.state.exists():
        state = load_gateway(
            args.state,
            args.variant,
            args.node,
            nodes,
            accept_edited=args.accept_edited_state,
            on_edited=lambda why: print(f"canergy gateway: warning: {why}", file=sys.stderr),
            seal=seal,
            up_variant=args.upstream_variant,
        )
    keep_books(args.state, seal, args.auth, fresh=state is None)
    return Gateway(
        args.node,
        nodes,
        variant=args.variant,
        up_variant=args.upstream_variant,
        up_timing=rule_timing(args, args.upstream_response_timeout),
        down_timing=rule_timing(args),
        state=state,
        start_without=start_without(args, nodes),
        below=make_below(core, args.id_base),
    )


def _config(args: argparse.Namespace, key: Key | None) -> SupervisorConfig:
    """The downstream supervisor's configuration; without a key it holds RETURNs for the
    node's confirmation (``--return-hold``), as ``canergy supervisor`` does. Its core is the
    gateway's (``_build``)."""
    service = ServiceConfig(
        policy=TopUp(args.target, args.min_grant) if args.target is not None else None,
        limits=grant_limits(args),
        status_path=args.status_file,
        status_stream=sys.stdout if args.status_file is None else None,
        status_period_us=args.status_period,
        lost_after_us=args.lost_after,
        stop_timeout_us=args.stop_timeout,
        fsync=not args.no_fsync,
        return_hold_us=None if key is not None else args.return_hold,
    )
    return SupervisorConfig(
        service=service,
        id_base=args.id_base,
        auth=auth_config(args, key),
        control_path=args.control,
    )


def _upstream_auth(
    args: argparse.Namespace, key: Key | None, codec: Codec, uplink: Uplink
) -> FrameAuth | None:
    """The upstream leg's authenticator (None without ``--upstream-auth``): the gateway's node
    key, the FD layout with ``--upstream-fd``; a JOIN (or a RESUME) gets 16 random bits above
    its nonce."""
    if key is None:
        return None
    layout = Layout.FD if getattr(args, "upstream_fd", False) else Layout.CLASSIC
    keys = frame_auth_keys(key)
    auth = FrameAuth(codec, layout, keys, Direction.TO_CLIENT, uplink.freshness)
    if uplink.join_nonce is not None:
        auth.join_fv[uplink.node] = secrets.randbits(16) << 16 | uplink.join_nonce
    elif uplink.gateway.up.state.phase is Phase.RESUMING:  # witnessed: so is a RESUME
        auth.resume_fv[uplink.node] = secrets.randbits(16) << 16 | uplink.gateway.up.state.nonce
    return auth


def _upstream_bus(args: argparse.Namespace, codec: Codec) -> Any:
    bus = open_bus(args, codec.client_watch_filters(args.node), prefix=UP)
    profile = FaultProfile(
        loss=args.upstream_loss, duplicate=args.upstream_duplicate, reorder=args.upstream_reorder
    )
    if not (profile.loss or profile.duplicate or profile.reorder):
        return bus
    from canergy.live.transports.faulty_bus import FaultyBus

    return FaultyBus(bus, FaultInjector(profile, random.Random(args.fault_seed)))


def _check_buses(args: argparse.Namespace) -> None:
    """The two legs are two buses (or two identifier blocks of one): a gateway that heard its
    own downstream frames as its upstream supervisor's would credit itself."""

    def flag(name: str) -> object:  # python-can leaves an option not given unset
        return getattr(args, name, None)

    same = (
        flag("interface") == flag("upstream_interface")
        and flag("channel") == flag("upstream_channel")
        and args.id_base == args.upstream_id_base
    )
    if same:
        raise ValueError(
            "the upstream and downstream buses are the same bus and identifier block: give "
            "--upstream-channel another bus (or --upstream-id-base another block)"
        )


def run(args: argparse.Namespace) -> int:
    if args.target is not None and args.target < QUANTUM_UJ:
        raise ValueError("--target must be at least 1 mJ")
    _check_buses(args)
    check_widths(args)
    check_state(args)
    start_without(args, tuple(args.nodes))  # checked before the state file is touched
    core = core_choice(args)  # so is --core c where the C core cannot run
    up_key, down_key = _keys(args)
    now = monotonic_us()
    gateway, new = _build(args, down_key, core)
    files = GatewayFiles(gateway, args.state, fsync=not args.no_fsync)
    config = _config(args, down_key)
    down_codec, up_codec = Codec(args.id_base), Codec(args.upstream_id_base)
    down_bus = open_bus(args, down_codec.supervisor_watch_filters())
    up_bus = None
    built = None
    group = None
    try:
        up_bus = _upstream_bus(args, up_codec)
        up_counters = BusCounters()
        uplink = Uplink(
            gateway,
            UplinkConfig(telemetry_period_us=args.telemetry_period, return_above=args.return_above),
            files,
            now,
            counters=up_counters,
        )
        if not new:  # a start is a restart from the one record (witnessed above: RESUME)
            uplink.start_with_books(secrets.randbits(16), now, secrets.randbits(16))
        if new or uplink.joining:  # JOINING before the first save: a blank record is untrusted
            uplink.start_without_books(secrets.randbits(16), now)
        # the control socket, then the downstream role, which saves once
        built = build_supervisor(
            config, [down_bus], core=gateway.down, save=files.save, uplink=uplink
        )
        up = BusRuntime(
            up_bus,
            uplink,
            codec=up_codec,
            receives=Direction.TO_CLIENT,
            auth=_upstream_auth(args, up_key, up_codec, uplink),
            counters=up_counters,
        )
        group = BusGroup([up, built.loop])
        warn_no_fsync("canergy gateway", args.no_fsync)
        serve_supervisor(group, built.service, built.control)
    finally:
        if group is not None:
            group.close()
        if built is not None:
            built.close()
        for bus in (up_bus, down_bus):
            if bus is not None:
                bus.shutdown()
    return 0
