"""The live stack on python-can's virtual bus, and python-canopen SDO writes on the same bus kind.

canergy: a supervisor service and a firmware node host, each with its own bus end and loop thread
(as two processes would be), one-shot grants kept in flight for every node; per-transaction
latency from request to resolution; the CPU of the supervisor's loop thread and of the nodes'
measured apart. Baseline: a ``canopen.LocalNode`` serving expedited SDO downloads of 4 bytes to a
``RemoteNode`` client, one at a time, in the same process. ``canergy.bench.on_bus`` runs the same
measurement on a real interface, the nodes and the SDO server in processes of their own.

The nodes come from a client emulator registered under the ``canergy.emulators`` entry-point
group (the way python-can finds its interfaces): canergy names none and depends on none, and a
host-only install without one skips this part (see ``load_emulator``).
"""

from __future__ import annotations

import cProfile
import itertools
import pstats
import statistics
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, Protocol

import can
import canopen

from canergy.codec import Codec
from canergy.core import Timing
from canergy.live.runtime import BusRuntime, Handler, monotonic_us
from canergy.live.supervisor.build import CoreConfig, SupervisorConfig, build_supervisor
from canergy.live.supervisor.service import ServiceConfig
from canergy.messages import Direction

TIMING = Timing(response_timeout_us=500_000, retries=3, command_timeout_us=1_000_000)


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


EMULATORS = "canergy.emulators"


class Emulator(Protocol):
    """What a client emulator offers the benchmark: a host of nodes and its NV record size."""

    nv_record_bytes: int
    nv_file_bytes: int
    label: str
    """How reports name the node processes ``command`` starts (e.g. the command, short)."""

    def node_host(self, nodes: Sequence[int], nv_dir: Path, timing: Timing, now: int) -> Handler:
        """Nodes with NV files under ``nv_dir``, behind one bus handler."""
        ...

    def command(self, nodes: str, nv_dir: Path, bus_flags: Sequence[str]) -> list[str]:
        """A command line running ``nodes`` (e.g. ``1-16``) on the bus ``bus_flags`` name,
        with NV files under ``nv_dir`` (``canergy bench`` on a real interface)."""
        ...


class EmulatorMissing(Exception):
    """No registered client emulator loads here; the message says why."""


def load_emulator() -> Emulator:
    """The first client emulator of the ``canergy.emulators`` group that loads."""
    reasons = []
    for point in entry_points(group=EMULATORS):
        try:
            emulator: Emulator = point.load()
        except ImportError as exc:
            reasons.append(f"{point.value}: {exc}")
            continue
        return emulator
    why = "; ".join(reasons) or f"none registered under the {EMULATORS} entry points"
    raise EmulatorMissing(
        f"skipped the live stack and the client NV figures: they need a client emulator ({why})"
    )


def _no_clock() -> float:
    return 0.0


class TimedBus(can.BusABC):
    """A loop's bus with the CPU its ``send`` and ``recv`` take counted (the driver's share of
    a frame, measured where it is spent: copies, queues, waits and system calls) and, while
    ``stamps`` is a list, the time each frame left or arrived (``(perf_counter, sent)``)."""

    def __init__(self, bus: can.BusABC, *, cpu: bool = True) -> None:
        """``cpu`` False: stamps only (a thread's CPU clock is a system call per reading)."""
        self.bus = bus  # nothing of BusABC's own state is used
        self.spent = 0.0
        self.stamps: list[tuple[float, bool]] | None = None
        self._clock = time.thread_time if cpu else _no_clock
        self._is_shutdown = True  # the wrapped bus is shut down by its owner

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        start = self._clock()
        if (stamps := self.stamps) is not None:  # read once: another thread may clear it
            stamps.append((time.perf_counter(), True))
        try:
            self.bus.send(msg, timeout)
        finally:
            self.spent += self._clock() - start

    def recv(self, timeout: float | None = None) -> can.Message | None:
        start = self._clock()
        try:
            msg = self.bus.recv(timeout)
        finally:
            self.spent += self._clock() - start
        if msg is not None and (stamps := self.stamps) is not None:
            stamps.append((time.perf_counter(), False))
        return msg

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        raise NotImplementedError  # recv is forwarded whole

    @property
    def state(self) -> can.BusState:
        return self.bus.state

    @state.setter
    def state(self, new_state: can.BusState) -> None:
        self.bus.state = new_state


def turn_us(stamps: Sequence[tuple[float, bool]]) -> float | None:
    """The median time (µs) from a frame received to the next frame sent: one side's turn in
    a one-node exchange (its decode, rules and encode, as the latency sees them)."""
    gaps = [b[0] - a[0] for a, b in itertools.pairwise(stamps) if not a[1] and b[1]]
    return 1e6 * statistics.median(gaps) if gaps else None


def latency_profile(
    latency_ms: float | None, supervisor_us: float | None, nodes_us: float | None
) -> dict[str, float | None] | None:
    """Where a one-node transaction's time goes: two turns of the supervisor (ACK to COMMIT,
    and the request to INTENTION with COMMITTED's handling), two of the node (INTENTION to
    ACK, COMMIT to COMMITTED) and four bus hops (a send, the receiver's wake-up, its receive),
    derived as what is left. ``nodes_us`` None: the nodes' side is not seen (other process)."""
    if latency_ms is None or supervisor_us is None:
        return None
    rest = 1e3 * latency_ms - 2 * supervisor_us
    return {
        "supervisor_turn_us": supervisor_us,
        "nodes_turn_us": nodes_us,
        "bus_hop_us": None if nodes_us is None else (rest - 2 * nodes_us) / 4,
        "nodes_and_bus_us": rest,
    }


class NoAnswer(RuntimeError):
    """The nodes did not complete a first transaction each in time (emulator not on the bus)."""


def _thread_cpu(thread: threading.Thread) -> float:
    """CPU seconds ``thread`` has used so far (Linux: its own clock; elsewhere 0)."""
    assert thread.ident is not None
    try:
        return time.clock_gettime(time.pthread_getcpuclockid(thread.ident))
    except (AttributeError, OSError):  # no per-thread clocks on this platform
        return 0.0


def drive_grants(
    bus: can.BusABC,
    nodes: Sequence[int],
    duration_s: float,
    *,
    others: Sequence[BusRuntime] = (),
    warm_up_s: float = 10.0,
    profile: cProfile.Profile | None = None,
    node_clocks: Sequence[Callable[[], float | None]] = (),
    state_path: Path | None = None,
    core: str = "python",
    codec: Codec | None = None,
) -> dict[str, Any]:
    """A supervisor on ``bus`` keeps one grant of 1 mJ in flight to each of ``nodes`` for
    ``duration_s``, after a warm-up in which every node completes a transaction. ``others``:
    loops to run in threads of their own (in-process nodes). Measured in the window only:
    transactions, latency from request to COMMITTED, frames the supervisor sent and received,
    the CPU of the supervisor's loop thread (and of it, what its bus's ``send`` and ``recv``
    took) and of the other loops' threads. ``profile``:
    profile the supervisor's loop thread (figures then include the profiler's cost).
    ``node_clocks``: CPU clocks (seconds; None: unreadable) of node processes, read at the
    window's ends like the threads' clocks. ``state_path``: the supervisor keeps its books
    there, as ``canergy supervisor --state`` does (without fsync: its cost is the disk's).
    ``core``: the supervisor core, "python" or "c" (``canergy supervisor --core``); ``codec``:
    the bus's identifier block (default: canergy's)."""
    codec = codec or Codec()
    config = SupervisorConfig(
        core=CoreConfig(tuple(nodes), 10**15, timing=TIMING, kind=core),
        service=ServiceConfig(status_period_us=10**12, fsync=False, state_path=state_path),
        id_base=codec.id_base,
    )
    timed = TimedBus(bus)
    built = build_supervisor(config, [timed])
    service, runtime = built.service, built.loop
    stop, measuring = threading.Event(), threading.Event()
    latencies: list[float] = []
    warmed: set[int] = set()
    all_warm = threading.Event()

    def ask(node: int) -> None:
        started = time.perf_counter()

        def reply(result: dict[str, Any]) -> None:  # runs in the supervisor's loop thread
            if result.get("outcome") == "COMMITTED":
                if measuring.is_set():
                    latencies.append(time.perf_counter() - started)
                warmed.add(node)
                if len(warmed) == len(nodes):
                    all_warm.set()
            if not stop.is_set():
                ask(node)  # keep one grant in flight per node

        service.request_grant(node, 1_000, reply)

    for n in nodes:  # queued before the loops start
        ask(n)

    def supervise() -> None:
        if profile is not None:
            profile.enable()
        try:
            runtime.run(stop.is_set, 0.01)
        finally:
            if profile is not None:
                profile.disable()

    threads = [threading.Thread(target=supervise, daemon=True)] + [
        threading.Thread(target=r.run, args=(stop.is_set, 0.01), daemon=True) for r in others
    ]
    for t in threads:
        t.start()
    try:
        if not all_warm.wait(warm_up_s):
            missing = sorted(set(nodes) - warmed)
            raise NoAnswer(
                f"{len(missing)} of {len(nodes)} node(s) completed no transaction in "
                f"{warm_up_s:g} s (first: {missing[:5]}): is the emulator on this bus?"
            )
        counters = runtime.counters
        sent0, received0, telemetry0, saves0 = (
            counters.frames_sent,
            counters.frames_received,
            service.telemetry_heard,
            service.ledger.saves,
        )
        cpu0, bus0 = [_thread_cpu(t) for t in threads], timed.spent
        nodes0 = [clock() for clock in node_clocks]
        stamped = [timed, *(r.bus for r in others if isinstance(r.bus, TimedBus))]
        for b in stamped if len(nodes) == 1 else ():
            b.stamps = []
        start = time.perf_counter()
        measuring.set()
        time.sleep(duration_s)
        measuring.clear()
        elapsed = time.perf_counter() - start
        turns = [turn_us(b.stamps) if b.stamps is not None else None for b in stamped]
        for b in stamped:
            b.stamps = None
        cpu = [_thread_cpu(t) - c for t, c in zip(threads, cpu0, strict=True)]
        in_bus = timed.spent - bus0
        nodes1 = [clock() for clock in node_clocks]
        sent, received = counters.frames_sent - sent0, counters.frames_received - received0
        frames = sent + received
        telemetry = service.telemetry_heard - telemetry0
        saves = service.ledger.saves - saves0
        done = len(latencies)
    finally:
        stop.set()
        for t in threads:
            t.join(timeout=10)
    return {
        "nodes": len(nodes),
        "core": core,
        "transactions": done,
        "tx_per_s": done / elapsed,
        "latency_p50_ms": 1e3 * _percentile(latencies, 0.5) if done else None,
        "latency_p99_ms": 1e3 * _percentile(latencies, 0.99) if done else None,
        "frames_sent": sent,
        "frames_received": received,
        "frames_per_tx": (frames - telemetry) / done if done else None,
        "telemetry_per_tx": telemetry / done if done else None,
        "supervisor_cpu_us_per_frame": 1e6 * cpu[0] / frames if frames else None,
        "bus_cpu_us_per_frame": 1e6 * in_bus / frames if frames else None,
        "nodes_cpu_us_per_frame": _per_frame(cpu[1:], nodes0, nodes1, frames),
        "state_file": state_path is not None,
        "saves_per_tx": saves / done if done else None,
        "latency_profile": latency_profile(
            1e3 * _percentile(latencies, 0.5) if done else None,
            turns[0],
            turns[1] if len(turns) > 1 else None,
        ),
    }


def _per_frame(
    threads: list[float], before: list[float | None], after: list[float | None], frames: int
) -> float | None:
    """The nodes' CPU (their threads here, their processes' clocks) per frame, or None."""
    spent = threads + [b - a for a, b in zip(before, after, strict=True) if a is not None and b]
    return 1e6 * sum(spent) / frames if spent and frames else None


def canergy_grants(
    emulator: Emulator,
    nodes: int,
    duration_s: float,
    nv_dir: Path,
    profile: cProfile.Profile | None = None,
    state_file: bool = False,
    core: str = "python",
    id_base: int | None = None,
) -> dict[str, Any]:
    """``drive_grants`` on python-can's virtual bus, the emulator's nodes in a thread of this
    process (a bus end and a loop of their own, as another process would have); ``state_file``:
    the supervisor's books in ``nv_dir``; ``id_base``: the identifier block (default canergy's)."""
    channel = f"bench-{uuid.uuid4().hex}"
    codec = Codec() if id_base is None else Codec(id_base)
    ids = list(range(1, nodes + 1))
    host = emulator.node_host(ids, nv_dir, TIMING, monotonic_us())
    sup_bus = can.Bus(interface="virtual", channel=channel, can_filters=codec.supervisor_filters())
    node_bus = can.Bus(interface="virtual", channel=channel)
    node_loop = BusRuntime(
        TimedBus(node_bus, cpu=False), host, codec=codec, receives=Direction.TO_CLIENT
    )
    try:
        books = nv_dir / "supervisor.json" if state_file else None
        return drive_grants(
            sup_bus,
            ids,
            duration_s,
            others=[node_loop],
            profile=profile,
            state_path=books,
            core=core,
            codec=codec,
        )
    finally:
        sup_bus.shutdown()
        node_bus.shutdown()


def bare_round_trips(count: int, timeout_s: float = 5.0) -> float:
    """p50 (ms) of two frame round trips on python-can's virtual bus between this thread and
    an echo thread, bare python-can: the floor of a two-round-trip exchange on this bus, in the
    same process as the SDO baseline's. ``NoAnswer`` when an echo takes over ``timeout_s``."""
    channel = f"echo-{uuid.uuid4().hex}"
    ours = can.Bus(interface="virtual", channel=channel)
    try:
        echo = can.Bus(interface="virtual", channel=channel)
    except BaseException:
        ours.shutdown()
        raise
    stop = threading.Event()

    def answer() -> None:
        while not stop.is_set():
            if (msg := echo.recv(0.01)) is not None:
                echo.send(can.Message(arbitration_id=msg.arbitration_id | 0x80, data=msg.data))

    thread = threading.Thread(target=answer, daemon=True)
    thread.start()
    latencies = []
    try:
        for i in range(count):
            start = time.perf_counter()
            for _ in range(2):
                ours.send(can.Message(arbitration_id=0x100, data=i.to_bytes(4, "little")))
                if ours.recv(timeout_s) is None:
                    raise NoAnswer(f"the echo thread did not answer in {timeout_s:g} s")
            latencies.append(time.perf_counter() - start)
    finally:
        stop.set()
        thread.join(timeout=5)
        ours.shutdown()
        echo.shutdown()
    return 1e3 * statistics.median(latencies)


def sdo_dictionary() -> canopen.ObjectDictionary:
    """One writable UNSIGNED32 at 0x2000:00: what the SDO baseline writes."""
    od = canopen.ObjectDictionary()
    var = canopen.objectdictionary.ODVariable("Value", 0x2000, 0)
    var.data_type = canopen.objectdictionary.UNSIGNED32
    var.access_type = "rw"
    od.add_object(var)
    return od


def sdo_latencies(remote: canopen.RemoteNode, count: int) -> dict[str, Any]:
    """``count`` expedited 4-byte downloads to ``remote``, one at a time."""
    remote.sdo.RESPONSE_TIMEOUT = 5.0
    latencies = []
    start = time.perf_counter()
    for i in range(count):
        t = time.perf_counter()
        remote.sdo.download(0x2000, 0, i.to_bytes(4, "little"))
        latencies.append(time.perf_counter() - t)
    elapsed = time.perf_counter() - start
    return {
        "writes": count,
        "writes_per_s": count / elapsed,
        "latency_p50_ms": 1e3 * statistics.median(latencies),
        "latency_p99_ms": 1e3 * _percentile(latencies, 0.99),
        "frames_per_write": 2,
    }


def sdo_writes(count: int) -> dict[str, Any]:
    """The SDO baseline on python-can's virtual bus: server and client in this process."""
    channel = f"sdo-{uuid.uuid4().hex}"
    od = sdo_dictionary()
    server_net, client_net = canopen.Network(), canopen.Network()
    server_net.connect(interface="virtual", channel=channel)
    client_net.connect(interface="virtual", channel=channel)
    try:
        server_net.add_node(canopen.LocalNode(5, od))
        return sdo_latencies(client_net.add_node(canopen.RemoteNode(5, od)), count)
    finally:
        server_net.disconnect()
        client_net.disconnect()


def top_functions(profile: cProfile.Profile, count: int = 12) -> list[dict[str, Any]]:
    """The functions that used the most time of their own, with their share of the total."""
    stats = pstats.Stats(profile)
    table: dict[Any, Any] = stats.stats  # type: ignore[attr-defined]
    total = sum(row[2] for row in table.values()) or 1.0
    rows = sorted(table.items(), key=lambda item: item[1][2], reverse=True)[:count]
    return [
        {
            "function": f"{Path(file).name}:{line}({name})",
            "calls": row[1],
            "own_share": round(row[2] / total, 3),
            "with_callees_share": round(row[3] / total, 3),
        }
        for (file, line, name), row in rows
    ]
