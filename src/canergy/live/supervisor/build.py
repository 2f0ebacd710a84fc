"""The one place a supervisor is put together.

``build_supervisor`` takes a ``SupervisorConfig`` (plain data: no ``argparse`` here; the
commands make it from their flags in ``canergy.cli``) and the bus or buses it runs on, and
returns it ready to serve: the core (from its books when they exist), the CANopen manager, the
guarded drives and devices, the service, its bus loop, each given what it needs through its
constructor. Nothing is assigned onto a built object afterwards.

A guarded device group (``DeviceGroup``: ODrive axes, moteus controllers, MIT-mode motors)
plugs in as one more entry of ``SupervisorConfig.devices``: it names its nodes and opens a guard
and a link per node on the bus; the builder adds each link to the bus's one Notifier, starts it
and puts the guards in front of the service (``canergy.live.canopen.cia402_host``).
"""

from __future__ import annotations

import secrets
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, cast

import can

from canergy.auth.state_key import state_seal
from canergy.bus_keys import bus_of, node_of
from canergy.ccore.supervisor import make_supervisor
from canergy.codec import DEFAULT_ID_BASE, Codec
from canergy.core import Timing
from canergy.core.supervisor import SupervisorCore
from canergy.live.atomic import kept_by
from canergy.live.bus_group import BusGroup
from canergy.live.devices.on_stuck import OnStuck
from canergy.live.runtime import BusCounters, BusRuntime, monotonic_us
from canergy.live.supervisor.control import ControlServer
from canergy.live.supervisor.frame_path import CoreFramePath, Pass
from canergy.live.supervisor.grants import GrantDesk
from canergy.live.supervisor.intrusions import Intrusions, Refusals
from canergy.live.supervisor.joins import JoinHold
from canergy.live.supervisor.ledger import Ledger
from canergy.live.supervisor.nodes import NodeInfo, lost, name_of
from canergy.live.supervisor.outputs import BooksOut, StatusOut
from canergy.live.supervisor.rules_said import RulesSaid
from canergy.live.supervisor.service import ServiceConfig, ServiceParts, SupervisorService
from canergy.live.supervisor.state_file import keep_books, load_state
from canergy.live.supervisor.status import StatusReport
from canergy.live.supervisor.stopping import Stopping
from canergy.live.supervisor.telemetry import HeardTable, TelemetryTable
from canergy.live.supervisor.watch import BusWatch
from canergy.live.supervisor.witness import ReturnGate
from canergy.messages import Direction

if TYPE_CHECKING:  # the guarded drives' modules load only when a build has some
    from canergy.live.canopen.cia402_host import GuardedDevice, GuardedDevices, HostBeat

Clock = Callable[[], int]


@dataclass(frozen=True, slots=True)
class CoreConfig:
    """The rules and the books: which core runs which rules for which nodes, from which file."""

    nodes: tuple[int, ...]
    """The nodes (over several buses: session keys, ``canergy.bus_keys``)."""
    initial_uj: int
    variant: str = "hardened"
    timing: Timing | None = None
    kind: str = "python"
    """"python" or "c" (already resolved: ``--core auto`` is one of them here)."""
    state_path: Path | None = None
    """The books: loaded when the file exists (a start is then a restart)."""
    accept_edited: bool = False
    start_without: frozenset[int] = frozenset()
    keep_books: bool = True
    """Claim the books for this process (sealed with the key, if any); False: listen-only."""
    warn: Callable[[str], None] | None = None
    """Told of an edited state file accepted (``--accept-edited-state``)."""


@dataclass(frozen=True, slots=True)
class AuthConfig:
    """Authenticated mode (``--auth``): the master key, its file, the frame layout."""

    key: Any
    """A ``canergy.auth.keys.Key`` (master): it seals the books, and every bus's frames but
    where ``bus_keys`` names another."""
    path: Path | None = None
    """The key's file: the epochs record of the books it sealed is kept beside it."""
    fd: bool = False
    bus_keys: tuple[Any, ...] = ()
    """Over several buses: each bus's master key, in ``ServiceConfig.bus_names``' order (empty:
    ``key`` on every bus). A node id on two buses needs two different keys there
    (``check_keys``)."""

    def key_of(self, bus: int) -> Any:
        """The master key of the bus at index ``bus``."""
        return self.bus_keys[bus] if self.bus_keys else self.key


@dataclass(frozen=True, slots=True)
class CanopenConfig:
    """CANopen on the same bus (``--canopen``): NMT, heartbeat watchdog, SDO audit."""

    nodes: tuple[int, ...]
    eds: Path
    heartbeat_timeout_us: int


class Cia402Group(Protocol):
    """Guarded CiA 402 drives (``--cia402``): a guard and a link per drive."""

    @property
    def nodes(self) -> tuple[int, ...]: ...

    def open(
        self, network: Any, now: int, clock: Clock
    ) -> tuple[dict[int, tuple[Any, Any]], HostBeat, can.Listener | None]:
        """Drives (node: (``DriveGuard``, ``DriveLink``)) on the CANopen ``network``, the
        host's heartbeat, and the capture of the in-process leg (None: none)."""
        ...


class DeviceGroup(Protocol):
    """Guarded devices of one profile (``--odrive``, ``--moteus``, ``--mit``): a guard and a
    link per node."""

    @property
    def nodes(self) -> tuple[int, ...]: ...

    def open(
        self, bus: can.BusABC, now: int, clock: Clock, wake: Callable[[], None]
    ) -> Mapping[int, GuardedDevice]:
        """A guard and a link per node; the builder adds each link to the bus's Notifier and
        starts it. ``wake``: the bus loop runs a pass at once (a link with work from elsewhere
        than the bus calls it; the pass pumps the links)."""
        ...


@dataclass(frozen=True, slots=True)
class SupervisorConfig:
    """Everything a supervisor needs but its bus: made from the flags in ``canergy.cli``."""

    core: CoreConfig | None = None
    """None: the core is handed to the builder (a gateway's downstream role is its
    ``Gateway``'s)."""
    service: ServiceConfig = field(default_factory=ServiceConfig)
    id_base: int = DEFAULT_ID_BASE
    auth: AuthConfig | None = None
    control_path: Path | None = None
    canopen: CanopenConfig | None = None
    cia402: Cia402Group | None = None
    devices: tuple[DeviceGroup, ...] = ()
    report: Callable[[str], None] | None = None
    """Told in one line whenever a guard stops or releases its drive or device."""
    on_stuck: str | None = None
    """``--on-stuck``: the command run once each time a guarded device becomes STUCK."""
    max_batch: int = 512
    """The most frames a pass of the bus loop takes (``canergy bench --pace``: 1)."""

    @property
    def shares_bus(self) -> bool:
        """CANopen or guarded drives on the bus: one Notifier owns it (11-bit frames too)."""
        return self.canopen is not None or self.cia402 is not None or bool(self.devices)


def check_keys(config: SupervisorConfig, sessions: Sequence[int]) -> None:
    """Refuse (``ValueError``) two ``sessions`` (session keys, ``canergy.bus_keys``) of one
    node id on two buses under the same node key: a frame of one would verify as the other's
    on either bus. A node's key comes from its bus's master key and its id alone
    (``AuthConfig.key_of``), so with one master key a node id may be on one bus only."""
    auth, names = config.auth, config.service.bus_names
    if auth is None or not names:
        return
    if auth.bus_keys and len(auth.bus_keys) != len(names):
        raise ValueError(f"{len(auth.bus_keys)} bus keys for {len(names)} buses")
    check_session_keys(names, sessions, lambda bus, node: auth.key_of(bus).node_key(node))


def check_session_keys(
    names: Sequence[str], sessions: Iterable[int], node_key: Callable[[int, int], bytes]
) -> None:
    """``check_keys`` with each session's node key given: ``node_key(bus index, node id)``."""
    seen: dict[tuple[int, bytes], int] = {}
    for session in sessions:
        bus, node = bus_of(session), node_of(session)
        key = (node, node_key(bus, node))
        if key in seen:
            raise ValueError(
                f"node {node} is on bus {names[seen[key]]} and on bus {names[bus]} under the "
                "same key (a node's key comes from the master key and its id alone): a frame "
                "of one would verify as the other's; give every node a different id"
            )
        seen[key] = bus


ASK_IT = " (a running supervisor or gateway takes grants through its --control socket)"
"""What a refusal to keep a state file another keeper holds adds."""


def open_core(config: SupervisorConfig, now: int | None = None) -> SupervisorCore:
    """The core, from its books when the file exists (a start is then a restart: the core is
    told of the power loss with a fresh nonce). Refused before anything is read or written
    when two of its sessions would share a key (``check_keys``), or while another core keeps
    the books (``kept_by``: in this process or another, until that core is collected)."""
    c = config.core
    if c is None:
        raise ValueError("no core configured (SupervisorConfig.core) and none handed over")
    check_keys(config, c.nodes)
    kept = c.state_path if c.keep_books else None
    opened = partial(_from_books, config, c, now)
    return opened() if kept is None else kept_by(kept, "state file", opened, hint=ASK_IT)


def _from_books(config: SupervisorConfig, c: CoreConfig, now: int | None) -> SupervisorCore:
    """``open_core``'s core (the state file's lock, if kept, is already held)."""
    auth, buses = config.auth, config.service.bus_names
    seal = None if auth is None else state_seal(auth.key)
    state = None
    if c.state_path is not None and c.state_path.exists():
        state = load_state(
            c.state_path,
            c.variant,
            c.nodes,
            buses=buses,
            accept_edited=c.accept_edited,
            on_edited=c.warn,
            seal=seal,
        )
    if c.state_path is not None and c.keep_books:
        keep_books(c.state_path, seal, None if auth is None else auth.path, fresh=state is None)
    core = make_supervisor(
        c.kind,
        c.nodes,
        c.initial_uj,
        variant=c.variant,
        timing=c.timing,
        state=state,
        id_base=config.id_base,
        start_without=c.start_without,
        buses=bool(buses),
    )
    if state is not None:  # a start is a restart from the persistent record; witnessed: SYNC(n)
        core.power_loss(monotonic_us() if now is None else now, secrets.randbits(16))
    return core


def service_parts(
    core: SupervisorCore,
    config: ServiceConfig,
    *,
    save: Callable[[], None] | None = None,
    bus_counters: BusCounters | None = None,
    buses: Mapping[str, BusCounters] | None = None,
    liveness: Callable[[int, int], bool] | None = None,
    extra_status: Callable[[int], dict[str, Any]] | None = None,
    control: ControlServer | None = None,
) -> ServiceParts:
    """The service's parts, the core's own in C where it has them (``SupervisorCore.heard_table``,
    ``return_gate``, ``join_hold``, ``grant_caps``). ``save``: writes the books instead of
    ``config.state_path`` (a gateway keeps both of its roles in one file); ``bus_counters``: the
    bus loop's counters (one bus), or ``buses``: each bus's by name; ``liveness``: an extra
    liveness test (the CANopen heartbeat watchdog, the guarded drives'); ``extra_status``: more
    status under ``cia402`` (the guarded drives); ``control``: the control socket (its refusals
    are in the status)."""
    name = partial(name_of, config.bus_names)
    heard: TelemetryTable | None = core.heard_table(config.lost_after_us)
    if heard is None:
        heard = HeardTable(core.nodes, config.lost_after_us)
    nodes = {n: NodeInfo(heard.of(n)) for n in core.nodes}
    hold_us, block_us = config.return_hold_us or 0, config.witness_block_us
    witness = core.return_gate(hold_us, block_us, config.return_hold_us is not None)
    if witness is None:
        witness = ReturnGate(hold_us, block_us)
    books = BooksOut(core, config.state_path, fsync=config.fsync, buses=config.bus_names, save=save)
    caps = core.grant_caps(config.limits, config.policy)
    counters = BusCounters() if bus_counters is None else bus_counters
    by_bus = dict(buses or {})
    intrusions = Intrusions("supervisor", name=name)
    refusals = Refusals("supervisor", name=name)
    stopping = Stopping()
    watch = BusWatch(
        core,
        nodes,
        intrusions,
        refusals,
        tuple(by_bus.values()) or (counters,),
        listen_only=config.listen_only,
        stop_on_intrusion=config.stop_on_intrusion,
        stopping=stopping,
    )
    joining = (config.join_hold_us, config.local_nodes, intrusions, refusals)

    def authenticated() -> bool:
        return watch.authenticated

    joins = core.join_hold(*joining, authenticated)
    if joins is None:
        joins = JoinHold(core.nodes, *joining, authenticated)
    passes = Pass()
    path = CoreFramePath(core, max(1, len(config.bus_names)), config.listen_only, passes, stopping)
    is_lost = partial(lost, nodes, liveness, config.lost_after_us)
    report = StatusReport(
        core,
        nodes,
        witness,
        joins,
        intrusions,
        refusals,
        path,
        node_name=name,
        is_lost=is_lost,
        bus_counters=counters,
        buses=by_bus,
        control=control,
        extra_status=extra_status,
    )
    return ServiceParts(
        heard=heard,
        nodes=nodes,
        rules_said=RulesSaid(core.variant.name, nodes, config.local_nodes, name),
        desk=GrantDesk(config.limits, config.policy, caps),
        ledger=Ledger(core, books, listen_only=config.listen_only),
        status_out=StatusOut(config.status_path, config.status_stream, config.status_text),
        intrusions=intrusions,
        refusals=refusals,
        witness=witness,
        joins=joins,
        bus_counters=counters,
        buses=by_bus,
        passes=passes,
        stopping=stopping,
        watch=watch,
        path=path,
        report=report,
        is_lost=is_lost,
    )


def build_service(
    core: SupervisorCore,
    config: ServiceConfig,
    now: int,
    *,
    save: Callable[[], None] | None = None,
    liveness: Callable[[int, int], bool] | None = None,
    extra_status: Callable[[int], dict[str, Any]] | None = None,
    bus_counters: BusCounters | None = None,
    buses: Mapping[str, BusCounters] | None = None,
    control: ControlServer | None = None,
    uplink: Any = None,
) -> SupervisorService:
    """The service of ``core`` under ``config`` with its parts (``service_parts``), started at
    ``now``: the builder's, and the one unit tests make without a bus. ``uplink``: the gateway's
    upstream role (the service is then a ``DownstreamService``); ``liveness``, ``extra_status``
    and ``control`` as ``SupervisorService`` takes them."""
    parts = service_parts(
        core,
        config,
        save=save,
        bus_counters=bus_counters,
        buses=buses,
        liveness=liveness,
        extra_status=extra_status,
        control=control,
    )
    if uplink is not None:
        from canergy.live.gateway.process import DownstreamService

        return DownstreamService(core, config, now, parts, uplink=uplink, liveness=liveness)
    return SupervisorService(core, config, now, parts, liveness=liveness)


@dataclass(slots=True)
class RunningSupervisor:
    """A built supervisor: serve ``loop`` (``canergy.live.serve.serve_supervisor``), then
    ``close``. ``loop`` is None when it was built without a bus (its handler is then driven
    directly)."""

    service: SupervisorService
    handler: Any
    """The bus loop's ``Handler``: the service, or the guarded devices in front of it."""
    loop: Any
    runtimes: tuple[BusRuntime, ...]
    control: ControlServer | None
    manager: Any
    guarded: GuardedDevices | None
    networks: tuple[Any, ...]
    clock: Clock = monotonic_us

    def exit(self) -> None:
        """Before the last status: every guarded drive and device halted, its stop on the bus,
        and what its link heard until then metered and booked (``GuardedSupervisor.exit``);
        what that leaves for the bus sent."""
        if self.guarded is None:
            return
        out = self.handler.exit(self.clock)
        if self.loop is not None:
            self.loop.send_messages(out)

    def close(self, now: int | None = None) -> None:
        """Halt every guarded drive (an exit never leaves one running; ``exit`` did, unless
        the run ended on an error), stop the Notifier and the control socket; the buses stay
        open (their opener shuts them down)."""
        try:
            if self.guarded is not None:
                self.guarded.halt_all(monotonic_us() if now is None else now)
                self.guarded.close()
        finally:
            if isinstance(self.loop, BusGroup):
                self.loop.close()
            if self.control is not None:
                self.control.close()
            for network in self.networks:
                network.notifier.stop()


def build_supervisor(
    config: SupervisorConfig,
    buses: Sequence[can.BusABC] = (),
    *,
    core: SupervisorCore | None = None,
    save: Callable[[], None] | None = None,
    uplink: Any = None,
    heartbeat_bus: Any = None,
    clock: Clock = monotonic_us,
) -> RunningSupervisor:
    """The supervisor of ``config`` on ``buses`` (one, or one per ``config.service.bus_names``;
    none: the service and its handler only, driven by the caller). ``core``: instead of
    ``open_core(config)`` (a gateway's downstream role, whose core is its ``Gateway``'s);
    ``save``: writes the books instead of the state file; ``uplink``: the gateway's upstream
    role (the service is then a ``DownstreamService``); ``heartbeat_bus``: without a bus, where
    the guarded drives' host sends its heartbeat (a co-simulation's drives hear it there)."""
    names = config.service.bus_names
    if names and len(buses) != len(names):
        raise ValueError(f"{len(names)} bus names for {len(buses)} buses")
    if not names and len(buses) > 1:
        raise ValueError("several buses need their names (ServiceConfig.bus_names)")
    if names and config.shares_bus:
        raise ValueError("CANopen and guarded drives and devices work on one bus")
    sessions = core.nodes if core is not None else config.core and config.core.nodes
    check_keys(config, sessions or ())  # before the socket is bound
    made: list[Any] = []  # what to undo when a later step fails
    control = None
    try:
        # the socket first: a run that cannot bind it stops before the state file is written
        if config.control_path is not None:
            control = ControlServer(config.control_path)
        if core is None:
            core = open_core(config, clock())
        if names:
            return _several(config, buses, core, control, clock)
        bus = buses[0] if buses else None
        parts = _Parts(save, uplink, heartbeat_bus if bus is None else bus, clock)
        return _one(config, bus, core, control, parts, made)
    except BaseException:
        for undo in reversed(made):
            undo()
        if control is not None:
            control.close()
        raise


@dataclass(frozen=True, slots=True)
class _Parts:
    save: Callable[[], None] | None
    uplink: Any
    beat_bus: Any
    clock: Clock


def _one(
    config: SupervisorConfig,
    bus: can.BusABC | None,
    core: SupervisorCore,
    control: ControlServer | None,
    parts: _Parts,
    made: list[Callable[[], None]],
) -> RunningSupervisor:
    clock, save, uplink = parts.clock, parts.save, parts.uplink
    listen_only = config.service.listen_only
    codec = Codec(config.id_base)
    network = reader = manager = notifier = None
    if bus is not None and config.shares_bus:
        from canergy.live.canopen.shared_bus import shared_network

        network, reader = shared_network(bus)
        notifier = network.notifier
        assert notifier is not None
        made.append(notifier.stop)
    if config.canopen is not None:
        from canergy.live.canopen.manager import CanopenManager

        assert network is not None, "CANopen needs a bus"
        c = config.canopen
        manager = CanopenManager(network, c.nodes, c.eds, c.heartbeat_timeout_us, clock)
    guarded = None
    if config.cia402 is not None or config.devices:
        from canergy.live.canopen.cia402_host import GuardedDevices

        now = clock()
        drives: dict[int, tuple[Any, Any]] = {}
        beat = capture = None
        if config.cia402 is not None:
            drives, beat, capture = config.cia402.open(network, now, clock)
        devices: dict[int, GuardedDevice] = {}
        for group in config.devices:
            assert bus is not None and reader is not None, "guarded devices need a bus"
            devices.update(group.open(bus, now, clock, reader.wake))
        guarded = GuardedDevices(
            drives,
            parts.beat_bus,
            beat,
            now,
            devices=devices,
            capture=capture,
            report=config.report,
            on_stuck=None
            if config.on_stuck is None
            else OnStuck(config.on_stuck, config.report or print),
            liveness=None if manager is None else manager.alive,
            top_up=config.service.policy,
        )
        made.append(guarded.close)
    counters = BusCounters()
    liveness = guarded.alive if guarded is not None else None if manager is None else manager.alive
    service = build_service(
        core,
        config.service,
        clock(),
        save=save,
        liveness=liveness,
        extra_status=None if guarded is None else guarded.status,
        bus_counters=counters,
        control=control,
        uplink=uplink,
    )
    if manager is not None and not listen_only:
        manager.start_all()
    if guarded is not None:  # the devices' links start once the service stands, as they did
        for _, link in guarded.devices.values():
            assert notifier is not None
            notifier.add_listener(cast(can.Listener, link))
            link.start()
    handler: Any = service
    if guarded is not None:
        from canergy.live.canopen.cia402_host import GuardedSupervisor

        handler = GuardedSupervisor(service, guarded, codec=codec)
    runtime = None
    if bus is not None:
        auth = _frame_auth(config, codec, service.freshness)
        off = _LISTEN_OFF if listen_only else None
        runtime = BusRuntime(
            bus,
            handler,
            codec=codec,
            receives=Direction.TO_SUPERVISOR,
            listen_only=listen_only,
            source=reader,
            auth=auth,
            counters=counters,
            clock=clock,
            frame_path=handler.frame_path(off, auth),
            max_batch=config.max_batch,
        )
    return RunningSupervisor(
        service=service,
        handler=handler,
        loop=runtime,
        runtimes=() if runtime is None else (runtime,),
        control=control,
        manager=manager,
        guarded=guarded,
        networks=() if network is None else (network,),
        clock=clock,
    )


def _several(
    config: SupervisorConfig,
    buses: Sequence[can.BusABC],
    core: SupervisorCore,
    control: ControlServer | None,
    clock: Clock,
) -> RunningSupervisor:
    """One service over every bus, a port and a runtime per bus, one loop for them all."""
    from canergy.live.supervisor.multi_bus import BusPort, BusRouter

    codec = Codec(config.id_base)
    names = config.service.bus_names
    counters = {name: BusCounters() for name in names}
    service = build_service(core, config.service, clock(), buses=counters, control=control)
    router = BusRouter()
    off = _LISTEN_OFF if config.service.listen_only else None
    for i, (name, bus) in enumerate(zip(names, buses, strict=True)):
        port = BusPort(service, i, router, deadlines=i == 0)
        auth = _frame_auth(config, codec, port.freshness, i)
        router.runtimes.append(
            BusRuntime(
                bus,
                port,
                codec=codec,
                receives=Direction.TO_SUPERVISOR,
                listen_only=config.service.listen_only,
                auth=auth,
                counters=counters[name],
                clock=clock,
                frame_path=service.frame_path(off, auth, i),
                max_batch=config.max_batch,
            )
        )
    runtimes = tuple(router.runtimes)
    return RunningSupervisor(
        service=service,
        handler=service,
        loop=BusGroup(list(runtimes), config.max_batch),
        runtimes=runtimes,
        control=control,
        manager=None,
        guarded=None,
        networks=(),
    )


_LISTEN_OFF = "--listen-only: every frame is only read, on the usual path"


def _frame_auth(config: SupervisorConfig, codec: Codec, freshness: Any, bus: int = 0) -> Any:
    """The frame authenticator of authenticated mode on the bus at index ``bus`` (None without
    a key)."""
    if config.auth is None:
        return None
    from canergy.auth.frames import FrameAuth, Layout
    from canergy.auth.keys import frame_auth_keys

    layout = Layout.FD if config.auth.fd else Layout.CLASSIC
    keys = frame_auth_keys(config.auth.key_of(bus))
    return FrameAuth(codec, layout, keys, Direction.TO_SUPERVISOR, freshness)
