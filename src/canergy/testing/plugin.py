"""canergy's pytest plugin: a supervisor, buses and a fault-injecting bridge for integration tests
of nodes, and the books closed at teardown.

pytest loads it wherever canergy is installed (entry point ``pytest11``, name ``canergy``);
``-p no:canergy`` turns it off. Fixtures:

- ``canergy_bus``: the test's bus (``TestBus``): python-can's virtual bus on a fresh channel,
  or ``--canergy-interface``/``--canergy-channel``, or ``@pytest.mark.canergy(interface=...,
  channel=..., fd=True)``; ``sibling()`` another (for the far side of a bridge).
- ``canergy_spawn``: ``canergy_spawn(["./my-node", "-c", "{channel}", "--status-file",
  "{status}"], "node1", bus=...)`` starts a node under test as a process (not on the virtual
  bus, which no other process hears), its status file registered with the books.
- ``canergy_supervisor``: ``canergy_supervisor("--nodes", "1-3", "--initial", "10J", ...)``
  starts ``canergy supervisor`` on ``canergy_bus`` (or ``bus=``) with those flags
  (``SupervisorRun``: ``grant``, ``status``, ``wait_for``, ``intrusions``, ``stop``);
  ``auth=True``: authenticated mode with a master key it makes, ``node_key(n)`` each node's.
- ``canergy_bridge``: ``canergy_bridge(bus1, bus2, loss=0.1, duplicate=0.1, seed=7,
  partitions=["2s+1s"], power_cuts=["node1@3s+1s"])`` carries frames between two buses through
  seeded faults (``canergy.bridge``), until the end of the test, and kills the node process
  ``canergy_spawn`` named ``node1`` 3 s after its start and starts it again 1 s later; or
  ``schedule=`` a ``FaultSchedule`` (e.g. drawn by
  ``canergy.testing.strategies.fault_schedules()``); given none, the marker's
  ``faults="loss=0.1,duplicate=0.05,cut=node1@3s+1s"`` and ``seed``.
- ``canergy_books``: the run's ledger. Register the nodes' statuses with ``add_client`` (a
  status file, or a function returning a status dict); ``spawn(..., "{status}")`` registers
  its own. At teardown the bridges' power cuts still on are ended (the processes started
  again) and no more are made, the node processes that write a status file are given up to
  30 s to write it since their last start (up), every supervisor is stopped (settling its
  transactions), then
  the processes, then the bridges, and the books are closed over the last statuses: the test
  fails naming the first party that created energy. ``@pytest.mark.canergy(books=False)`` opts out.

A capture of the bus (``canergy-capture.log``, candump format) is kept in ``tmp_path`` for
``canergy audit`` and ``canergy plot``.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:  # imported where used: pytest loads this plugin in every run of the venv
    from canergy.bridge.link import Bridge
    from canergy.bridge.schedule import FaultSchedule
    from canergy.testing.bus import Process, TestBus
    from canergy.testing.supervisor import SupervisorRun

ClientSource = Path | Callable[[], dict[str, Any]]


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("canergy", "canergy: supervisor, buses and books for node tests")
    group.addoption(
        "--canergy-interface",
        default=None,
        help="python-can interface of canergy_bus (default: virtual)",
    )
    group.addoption("--canergy-channel", default=None, help="channel of canergy_bus (e.g. vcan0)")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "canergy(interface=None, channel=None, fd=False, books=True, faults='', seed=0, "
        "nodes=None): canergy_bus's interface and channel for this test; books=False: do not "
        "close the books at teardown; faults (e.g. "
        "'loss=0.1,duplicate=0.05,partition=2s+1s,cut=node1@3s+1s') "
        "and seed: canergy_bridge's when it is given none; nodes (e.g. '1-5'): "
        "canergy_supervisor's --nodes when it is given none",
    )


def _marker(request: pytest.FixtureRequest) -> dict[str, Any]:
    marker = request.node.get_closest_marker("canergy")
    return dict(marker.kwargs) if marker is not None else {}


class Books:
    """The run of one test: its supervisors, processes, bridges and clients, torn down in that
    order (``stop_all``), then the books closed (``verdict``). The fixtures keep one per test;
    a property test makes one per example (``Books(tmp)``, then ``supervisor``, ``bridge``,
    ``add_client``)."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.supervisors: list[SupervisorRun] = []
        self.processes: dict[str, Process] = {}
        """The node processes by name; a bridge's power cuts switch them by these names."""
        self.restores: list[Callable[[], None]] = []
        self.bridges: list[Callable[[], None]] = []
        self.clients: list[ClientSource] = []
        self.stops: list[Callable[[], object]] = []

    def add_client(self, source: ClientSource, stop: Callable[[], object] | None = None) -> None:
        """A node's status: its status file (read at teardown), or a function returning it (a
        node's, or an emulator's with several under ``nodes``). ``stop``: how to stop the node,
        called at teardown once the supervisors have stopped (and settled with it)."""
        self.clients.append(source)
        if stop is not None:
            self.stops.append(stop)

    def supervisor(
        self, bus: TestBus, flags: Sequence[str], name: str = "supervisor", auth: bool = False
    ) -> SupervisorRun:
        """``canergy supervisor`` started on ``bus`` with ``flags`` (``SupervisorRun``), its
        files in this run's directory; stopped by ``stop_all``, its books closed by
        ``verdict``."""
        from canergy.testing.supervisor import SupervisorRun

        run = SupervisorRun(bus, self.tmp, flags, name, auth)
        self.supervisors.append(run)
        return run

    def process(self, name: str, argv: Sequence[str], status: Path | None = None) -> Process:
        """A node process started in this run's directory (``Process``; ``status``: the status
        file it writes), stopped by ``stop_all``; a bridge's power cuts name it ``name``."""
        from canergy.testing.bus import Process

        if name in self.processes:
            raise ValueError(f"a node process named {name!r} already runs in this test")
        process = Process(name, argv, self.tmp, status)
        self.processes[name] = process
        return process

    def bridge(self, bus1: TestBus, bus2: TestBus, schedule: FaultSchedule) -> Bridge:
        """A bridge between ``bus1`` and ``bus2`` with ``schedule``'s faults, running in a thread
        until ``stop_all``; its power cuts switch this run's node processes (``process``) by
        name. ``stop_all`` ends the cuts first, before it stops the supervisors."""
        import threading

        from canergy.bridge.link import Bridge

        buses = (bus1.open(), bus2.open())
        bridge = Bridge(
            buses, schedule, names=(bus1.channel, bus2.channel), processes=self.processes
        )
        stop = threading.Event()
        thread = threading.Thread(target=bridge.run, args=(stop.is_set,), daemon=True)
        thread.start()

        def closing() -> None:
            stop.set()
            thread.join(10)
            bridge.close()
            for bus in buses:
                bus.shutdown()
            if bridge.power_errors:
                raise AssertionError(f"the bridge's power cuts: {'; '.join(bridge.power_errors)}")

        self.restores.append(bridge.restore_power)
        self.bridges.append(closing)
        return bridge

    def client_statuses(self) -> list[dict[str, Any]]:
        out: list[dict[str, Any]] = []
        for source in self.clients:
            status = source() if callable(source) else json.loads(Path(source).read_text())
            nodes = status.get("nodes")  # an emulator serving several nodes
            if "credited_uj" not in status and isinstance(nodes, dict):
                out.extend(nodes.values())
            else:
                out.append(status)
        return out

    def stop_all(self) -> None:
        """Stop every part, in order, even when one fails to stop; then raise the first
        failure."""
        steps: list[Callable[[], object]] = [
            *self.restores,  # every node up again, before the supervisors settle with them
            *(p.wait_started for p in self.processes.values()),
            *(s.stop for s in self.supervisors),
            *(p.stop for p in self.processes.values()),
            *self.stops,
            *self.bridges,
        ]
        self.bridges.clear()
        self.restores.clear()
        first: BaseException | None = None
        for step in steps:
            try:
                step()
            except Exception as exc:  # the others still stop
                first = first or exc
        if first is not None:
            raise first

    def verdict(self) -> str | None:
        """Why the books do not close (None: they close, or there is nothing to close)."""
        from canergy.testing.books import creation

        if not self.supervisors:
            return None
        if len(self.supervisors) > 1:  # which nodes are whose is the test's to say: never silent
            return (
                f"{len(self.supervisors)} supervisors in one test: the plugin closes the books "
                "of one; close them in the test (canergy.cli.ledger.tree_from_files, as "
                "canergy ledger --level does) and mark it @pytest.mark.canergy(books=False)"
            )
        status = json.loads(self.supervisors[0].status_file.read_text())
        clients = self.client_statuses()
        try:
            return creation(status, clients)
        except (ValueError, KeyError) as exc:  # statuses that do not match the supervisor's
            nodes = ", ".join(status.get("nodes", {})) or "none"
            given = ", ".join(str(c.get("node")) for c in clients) or "none"
            return (
                f"cannot close the books ({exc}): the supervisor's nodes are {nodes}, the "
                f"clients' statuses given are of {given}; register each node's status "
                "(canergy_books.add_client, or {status} in canergy_spawn's command) or opt out "
                "with @pytest.mark.canergy(books=False)"
            )


@pytest.fixture
def canergy_bus(request: pytest.FixtureRequest) -> TestBus:
    """The test's bus: virtual on a fresh channel unless an option or the marker says."""
    from canergy.testing.bus import TestBus

    marked = _marker(request)
    interface = marked.get("interface") or request.config.getoption("canergy_interface")
    channel = marked.get("channel") or request.config.getoption("canergy_channel")
    fd = bool(marked.get("fd", False))
    if interface in (None, "virtual"):
        return TestBus("virtual", channel, fd) if channel else TestBus.virtual(fd)
    if not channel:
        raise pytest.UsageError(f"canergy_bus on {interface}: give --canergy-channel")
    return TestBus(interface, channel, fd)


@pytest.fixture
def canergy_books(
    request: pytest.FixtureRequest, tmp_path: Path, canergy_bus: TestBus
) -> Iterator[Books]:
    """The run's parts and its books; closed at teardown unless ``canergy(books=False)``."""
    from canergy.testing.bus import Capture

    books = Books(tmp_path)
    capture = Capture(canergy_bus, tmp_path / "canergy-capture.log")
    try:
        yield books
    finally:
        try:
            books.stop_all()
        finally:
            capture.close()
    if not _marker(request).get("books", True):
        return
    why = books.verdict()
    if why is not None:
        pytest.fail(f"canergy: {why} (capture: {capture.path})", pytrace=False)


@pytest.fixture
def canergy_supervisor(
    request: pytest.FixtureRequest, canergy_books: Books, canergy_bus: TestBus
) -> Callable[..., SupervisorRun]:
    """``canergy_supervisor(*flags, bus=None, name="supervisor", auth=False)``: a started
    supervisor (``auth``: in authenticated mode, with a master key it makes); without
    ``--nodes`` among the flags, the marker's ``nodes`` (e.g. ``nodes="1-5"``)."""
    nodes = _marker(request).get("nodes")

    def start(
        *flags: str, bus: TestBus | None = None, name: str = "supervisor", auth: bool = False
    ) -> SupervisorRun:
        if nodes is not None and "--nodes" not in flags:
            flags = ("--nodes", str(nodes), *flags)
        return canergy_books.supervisor(bus or canergy_bus, flags, name, auth)

    return start


@pytest.fixture
def canergy_spawn(
    canergy_books: Books, canergy_bus: TestBus, tmp_path: Path
) -> Callable[..., Process]:
    """``canergy_spawn(argv, name, bus=None)``: a node under test as a process, ``{channel}``,
    ``{interface}``, ``{tmp}``, ``{python}`` and ``{status}`` (its status file, registered with
    the books) filled in, and an argument ``{bus}`` replaced by the bus's flags; stopped with
    SIGTERM at teardown (``power_cut()`` for SIGKILL). ``name`` names it to the bridge's power
    cuts (``cut=NAME@AT+FOR``)."""

    def spawn(argv: Sequence[str], name: str = "node", bus: TestBus | None = None) -> Process:
        on = bus or canergy_bus
        if on.interface == "virtual":
            raise ValueError(
                "a process never hears python-can's virtual bus of another process: give "
                "--canergy-interface socketcan --canergy-channel vcan0 (or the marker), or "
                "spawn it on TestBus.zenoh() behind a bridge"
            )
        status = tmp_path / f"{name}-status.json"
        filled: list[str] = []
        for a in argv:
            if a == "{bus}":
                filled.extend(on.flags)
            else:
                filled.append(on.fill(a, tmp=tmp_path, python=sys.executable, status=status))
        writes_status = any("{status}" in a for a in argv)
        process = canergy_books.process(name, filled, status if writes_status else None)
        if writes_status:
            canergy_books.add_client(status)
        return process

    return spawn


@pytest.fixture
def canergy_bridge(request: pytest.FixtureRequest, canergy_books: Books) -> Callable[..., Bridge]:
    """``canergy_bridge(bus1, bus2, schedule=None, seed=0, partitions=(), power_cuts=(),
    **faults)``: a running ``canergy.bridge.link.Bridge``. The faults: a ``FaultSchedule`` (e.g.
    drawn by ``canergy.testing.strategies.fault_schedules()``), or keywords as ``FaultProfile``
    takes them (``loss``, ``duplicate``, ``reorder``, ``corrupt``, ``delay_us``...; no delay
    unless given) with partitions as ``"AT+FOR"`` (e.g. ``"2s+1s"``) and power cuts of the
    test's node processes (``canergy_spawn``) as ``"NAME@AT+FOR"`` (e.g. ``"node1@3s+1s"``), or
    else the marker's ``faults="loss=0.1,partition=2s+1s,cut=node1@3s+1s"`` and ``seed``."""
    from canergy.bridge.schedule import FaultSchedule, Partition, PowerCut, parse_faults
    from canergy.faults import FaultProfile

    marked = _marker(request)

    def start(
        bus1: TestBus,
        bus2: TestBus,
        *,
        schedule: FaultSchedule | None = None,
        seed: int | None = None,
        partitions: Sequence[str] = (),
        power_cuts: Sequence[str] = (),
        **faults: Any,
    ) -> Bridge:
        if seed is None:
            seed = int(marked.get("seed", 0))
        if schedule is None and not faults and not partitions and not power_cuts:
            profile, cuts, power = parse_faults(str(marked.get("faults", "")))
            schedule = FaultSchedule(profile, seed, cuts, power)
        elif schedule is None:
            faults.setdefault("delay_us", 0)
            faults.setdefault("jitter_us", 0)
            cuts = tuple(Partition.parse(p) for p in partitions)
            power = tuple(PowerCut.parse(c) for c in power_cuts)
            schedule = FaultSchedule(FaultProfile(**faults), seed, cuts, power)
        return canergy_books.bridge(bus1, bus2, schedule)

    return start
