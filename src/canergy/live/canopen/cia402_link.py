"""One CiA 402 drive over python-canopen: set-up, TPDO values in, controlwords out.

``canopen.BaseNode402`` does the profile: it reads the drive's PDO configuration, keeps the
last TPDO values, decodes the statusword into a power state and writes the controlword by RPDO
(when mapped) or SDO. Where it does not fit a guard it is worked around, not rewritten:

- its ``state`` setter blocks (hard-coded 0.4-0.8 s timeouts per step) and, asked for QUICK STOP
  ACTIVE, walks a drive whose quick stop fell through to SWITCH ON DISABLED (option codes 1 and
  2) back up through READY TO SWITCH ON and SWITCHED ON, re-enabling it, or raises "Illegal
  state transition" when the state moves between its two reads. The guard never uses it: quick
  stop and disable are written as controlwords, and enabling goes one step at a time with the
  profile's own transition table, each step decided by the next TPDO;
- ``setup_pdos`` asserts ``nmt.state in 'PRE-OPERATIONAL'`` (a substring test) and so fails for
  a drive whose heartbeat was not heard yet: the PDO configuration is read here and the profile
  is set up with ``read_pdos=False``;
- SDO and RPDO writes happen in a worker thread, so a drive that does not answer never blocks
  the supervisor's loop. Controlwords go before the next SDO transfer of whatever else it is
  doing: a stop never waits behind a read-back of the whole configuration (seconds on a loaded
  venue, beside an application's transfers), which the bound would have to cover.

At set-up the link also writes the guard's limits (0x6072, 0x6073, 0x6080) closed and reads them
back, reads the quick stop deceleration 0x6085, times one controlword write (the drive's latency),
and, in counter mode, finds the counter object in a TPDO of the drive or of a power-meter node
(an object the EDS lacks is added from its width). Every later limits write is read back and the
answer queued for the guard.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import can
import canopen
from canopen.profiles.p402 import BaseNode402, State402

from canergy.cia402.counter import COUNTER_KEY, CounterConfig
from canergy.cia402.envelope import (
    QUICK_STOP_DECELERATION,
    Limits,
    Ratings,
    StopKind,
)
from canergy.cia402.guard import (
    CW_DISABLE_VOLTAGE,
    ENABLED,
    STATUSWORD_KEY,
    Command,
    LimitsCommand,
    VerifyCommand,
)
from canergy.cia402.meter import RATED_CURRENT, RATED_TORQUE, MeterConfig
from canergy.cia402.metering import DriveSetup
from canergy.cia402.profile import Cia402Profile
from canergy.cia402.watch import (
    NMT,
    SDO_REQUEST,
    Key,
    SdoWatch,
    Write,
    nmt_writes,
    pdo_writes,
)

log = logging.getLogger(__name__)

STATUSWORD = 0x6041
CONTROLWORD = 0x6040
HEARTBEAT_CONSUMER = 0x1016
EDS = Path(__file__).with_name("cia402.eds")
"""A generic CiA 402 drive (standard objects only), for drives given without their own EDS."""

Sample = tuple[int, dict[int, int], str | None, int]
"""When the host took the TPDO in (µs), its values, the power state its statusword shows, and
its age then (µs since the CAN frame was received: a backlog the loop has not read yet)."""
LimitsAnswer = tuple[Limits, bool | None, str]
"""Limits written; whether the drive read them back unchanged (None: no answer came through
the shared SDO server, so it is not known); what went wrong if not."""
UNSIGNED_TYPES = {8: 0x5, 16: 0x6, 32: 0x7, 64: 0x1B}
TYPE_MAX = {0x2: 2**7 - 1, 0x3: 2**15 - 1, 0x4: 2**31 - 1, 0x5: 2**8 - 1, 0x6: 2**16 - 1}
TYPE_MAX |= {0x7: 2**32 - 1}
"""The largest value of a limit object's data type: its reach when neither flag nor EDS says."""
Seen = tuple[int, Write, int]
"""When the host took a frame in (µs), what it wrote, and its age then (µs)."""
SDO_ERRORS = (canopen.SdoCommunicationError, canopen.SdoAbortedError, can.CanError)
SDO_ATTEMPTS = 5
T = TypeVar("T")


@dataclass(frozen=True, slots=True)
class LinkConfig:
    eds: Path = EDS
    meter: MeterConfig = field(default_factory=MeterConfig)
    limits: Limits | None = None
    """The guard's full limits (written closed at set-up)."""
    counter: CounterConfig | None = None
    stop: StopKind = StopKind.QUICK
    host_id: int = 127
    consumer_timeout_ms: int = 500
    """Written to the drive's 0x1016:1 with ``host_id``: it faults when the host goes silent."""
    sdo_timeout_s: float = 0.5
    setup_retry_s: float = 1.0
    reach: tuple[int | None, int | None, int | None] = (None, None, None)
    """0x6072, 0x6073, 0x6080 at most (flags); None: the EDS's HighLimit, else the type's."""


class SetupError(RuntimeError):
    """The drive answers but cannot be guarded as configured (e.g. a needed object unmapped)."""


def shared_sdo(
    transfer: Callable[[], T], pause: Callable[[float], object], attempts: int = SDO_ATTEMPTS
) -> T:
    """Run an SDO ``transfer``. A drive's default SDO server is shared by every master (the
    guard and the application's): a transfer garbled by another master's is tried again
    (``attempts`` in all, ``pause`` growing between). An abort may be the answer to another
    master's request: only one that comes twice in a row is the drive's."""
    aborted: int | None = None
    for attempt in range(1, attempts):
        try:
            return transfer()
        except canopen.SdoCommunicationError:
            aborted = None
        except canopen.SdoAbortedError as exc:
            if exc.code == aborted:
                raise
            aborted = exc.code
        pause(0.01 * attempt)
    return transfer()


def ensure_variable(od: Any, index: int, subindex: int, bits: int, name: str) -> None:
    """Add an unsigned object of ``bits`` to ``od`` where its EDS lacks it (a counter is
    manufacturer-specific: the command line gives its width, not the EDS)."""
    if index in od and (subindex == 0 or subindex in getattr(od[index], "subindices", {})):
        return
    if index in od:
        raise SetupError(f"0x{index:04X} is in the EDS but has no sub-index {subindex}")
    var = canopen.objectdictionary.ODVariable(name, index, subindex)
    var.data_type = UNSIGNED_TYPES[bits]
    var.access_type = "ro"
    var.pdo_mappable = True
    od.add_object(var)


def power_state(statusword: int) -> str:
    """The power state a statusword shows, by the profile's own masks (as ``BaseNode402.state``)."""
    for state, (mask, bits) in State402.SW_MASK.items():
        if statusword & mask == bits:
            return state
    return "UNKNOWN"


def enable_step(state: str) -> int | None:
    """The controlword for one step from ``state`` toward OPERATION ENABLED, by the profile's
    own transition table (None: no step from there, e.g. FAULT needs a reset first). From QUICK
    STOP ACTIVE it goes by SWITCH ON DISABLED (transition 12), never straight back (16): a quick
    stop someone else ordered is not cut short."""
    if state in ("FAULT", "FAULT REACTION ACTIVE"):
        return None
    if state == "QUICK STOP ACTIVE":
        return State402.TRANSITIONTABLE[(state, "SWITCH ON DISABLED")]
    if (state, ENABLED) in State402.TRANSITIONTABLE:
        return State402.TRANSITIONTABLE[(state, ENABLED)]
    nxt = State402.next_state_indirect(state)
    return None if nxt is None else State402.TRANSITIONTABLE.get((state, nxt))


class DriveLink:
    """The host's end of one drive. TPDO callbacks run in the Notifier's thread and only
    queue samples; the guard drains them in the supervisor's loop."""

    def __init__(
        self,
        network: canopen.Network,
        node_id: int,
        config: LinkConfig,
        clock: Callable[[], int],
    ) -> None:
        self.config = config
        self.clock = clock
        self.network = network
        self.node = BaseNode402(node_id, str(config.eds))
        self.node.sdo.RESPONSE_TIMEOUT = config.sdo_timeout_s
        network.add_node(self.node)
        self.meter_node: canopen.RemoteNode | None = None
        counter = config.counter
        if counter is not None and counter.node is not None:
            self.meter_node = canopen.RemoteNode(counter.node, str(EDS))
            self.meter_node.sdo.RESPONSE_TIMEOUT = config.sdo_timeout_s
            network.add_node(self.meter_node)
        self.samples: deque[Sample] = deque()
        self.limit_answers: deque[LimitsAnswer] = deque()
        self.writes: deque[Seen] = deque()
        """Frames to the drive from others: what they wrote."""
        self.verified: deque[tuple[int, dict[Key, int | None]]] = deque()
        self._sdo_watch = SdoWatch()
        network.subscribe(SDO_REQUEST + node_id, self._on_sdo_request)
        network.subscribe(NMT, self._on_nmt)
        self.ready_at: int | None = None
        self.setup: DriveSetup | None = None
        self.profile: Cia402Profile | None = None
        """The drive as a profile (from its ratings): what is read back and how it compares."""
        self.error: str | None = None
        self.commands_sent = 0
        self.command_failures = 0
        self.last_command: dict[str, Any] | None = None
        self.reaction_max_us = 0
        """Longest time from the TPDO that called for a stop to its controlword leaving."""
        self.latency_max_us = 0
        """Longest controlword write by SDO, set-up included (the drive's answer)."""
        self._jobs: queue.Queue[Command | LimitsCommand | VerifyCommand | None] = queue.Queue()
        self._controlwords: deque[Command] = deque()
        """Controlwords waiting: written before the next SDO transfer of any other job, so a
        stop never waits behind a read-back of the whole configuration."""
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._work, name=f"drive-{node_id}", daemon=True)
        self._thread.start()

    @property
    def node_id(self) -> int:
        return int(self.node.id or 0)

    # -- the supervisor's loop ------------------------------------------------------------
    def drain(self) -> list[Sample]:
        out: list[Sample] = []
        while self.samples:
            out.append(self.samples.popleft())
        return out

    def drain_limits(self) -> list[LimitsAnswer]:
        out: list[LimitsAnswer] = []
        while self.limit_answers:
            out.append(self.limit_answers.popleft())
        return out

    def drain_writes(self) -> list[Seen]:
        out: list[Seen] = []
        while self.writes:
            out.append(self.writes.popleft())
        return out

    def drain_verified(self) -> list[tuple[int, dict[Key, int | None]]]:
        out: list[tuple[int, dict[Key, int | None]]] = []
        while self.verified:
            out.append(self.verified.popleft())
        return out

    def pending(self) -> bool:
        """Samples or answers wait for the guard."""
        return bool(self.samples or self.limit_answers or self.writes or self.verified)

    def command(self, cmd: Command | LimitsCommand | VerifyCommand) -> None:
        if isinstance(cmd, Command):
            self._controlwords.append(cmd)
        self._jobs.put(cmd)

    def close(self) -> None:
        self._closed.set()
        self._jobs.put(None)
        self._thread.join(timeout=5)

    # -- the worker thread ----------------------------------------------------------------
    def _work(self) -> None:
        while not self._closed.is_set():
            self._disable()  # unguarded until set up: off first, at every attempt (best effort)
            try:
                self._setup()
                break
            except (SetupError, KeyError) as exc:  # KeyError: an object the EDS lacks
                self.error = f"cannot be guarded: {self._explain(exc)}"
                log.error("drive %d: %s; disabling it", self.node_id, self.error)
                self._disable()  # a drive the guard cannot meter must not run
                return
            except SDO_ERRORS as exc:
                self.error = f"set-up failed, retrying: {exc}"
                self._closed.wait(self.config.setup_retry_s)
        while True:
            cmd = self._jobs.get()
            if cmd is None:
                self._controlwords_first()  # a stop handed over as the host exits still goes out
                return
            self._controlwords_first()
            if not isinstance(cmd, Command):  # a controlword's job was done by the line above
                self._safely(cmd)

    def _controlwords_first(self) -> None:
        """Write the controlwords waiting, in order (the worker's thread, between transfers;
        once set up: until then the set-up's own transfers go first)."""
        while self.ready_at is not None and self._controlwords:
            self._safely(self._controlwords.popleft())

    def _pause(self, seconds: float) -> None:
        """Between two tries of a transfer another master garbled: controlwords first."""
        self._controlwords_first()
        self._closed.wait(seconds)

    def _safely(self, cmd: Command | LimitsCommand | VerifyCommand) -> None:
        try:
            self._execute(cmd)
        except Exception as exc:  # never lose the worker: the next stop must still go out
            self.command_failures += 1
            log.exception("drive %d: controlword not written: %s", self.node_id, exc)

    def _explain(self, exc: Exception) -> str:
        """A set-up failure that names the drive's EDS and the object."""
        if isinstance(exc, KeyError):
            what = str(exc.args[0]) if exc.args else "an object"
            return (
                f"drive {self.node_id}: {what} (EDS {self.config.eds}): give the drive's own "
                "EDS with --cia402-eds, or a metering mode that does not need that object"
            )
        return f"drive {self.node_id}: {exc}"

    def _setup(self) -> None:
        node, sdo = self.node, self.node.sdo
        rated_torque = int(sdo[RATED_TORQUE].raw)
        rated_current = int(sdo[RATED_CURRENT].raw)
        if rated_torque <= 0 or rated_current <= 0:
            raise SetupError(f"rated torque {rated_torque} mNm / current {rated_current} mA")
        meter = self.config.meter
        ratings = Ratings(
            rated_torque, rated_current, meter.velocity_unit_rad_s, meter.resistance_mohm
        )
        self.profile = Cia402Profile(ratings, self.config.stop)
        counter = self.config.counter
        if counter is not None:
            target = node if counter.node is None else self.meter_node
            assert target is not None
            ensure_variable(
                target.object_dictionary,
                counter.index,
                counter.subindex,
                counter.bits,
                "energy counter",
            )
        consumer = self.config.host_id << 16 | self.config.consumer_timeout_ms
        sdo[HEARTBEAT_CONSUMER][1].raw = consumer
        if int(sdo[HEARTBEAT_CONSUMER][1].raw) != consumer:
            raise SetupError("the drive did not keep its heartbeat consumer setting (0x1016:1)")
        node.tpdo.read()
        node.rpdo.read()
        p402_log = logging.getLogger("canopen.profiles.p402")
        level = p402_log.level
        p402_log.setLevel(logging.ERROR)  # its advice on op-mode PDOs: the guard needs none
        try:
            node.setup_402_state_machine(read_pdos=False)
        finally:
            p402_log.setLevel(level)
        mapped = set(node.tpdo_values)
        needed = [STATUSWORD, *meter.needs()]
        if counter is not None and counter.node is None:
            needed.append(counter.index)
        missing = [i for i in needed if i not in mapped]
        if missing:
            names = ", ".join(f"0x{i:04X}" for i in missing)
            raise SetupError(f"its TPDOs do not carry {names}: map them (see docs/guide/drives.md)")
        if counter is not None and counter.node is not None:
            self._setup_meter_node(counter)
        for tpdo in node.tpdo.values():
            if tpdo.enabled:
                tpdo.add_callback(self._on_tpdo)
        limits = self._setup_limits()
        deceleration = 0
        if self.config.stop is StopKind.QUICK and QUICK_STOP_DECELERATION in node.object_dictionary:
            deceleration = int(sdo[QUICK_STOP_DECELERATION].raw)
        latency = self._timed_controlword(CW_DISABLE_VOLTAGE)  # no budget yet: off, and timed
        config = self._read_config()
        self._watch_rpdos(config)
        node.nmt.state = "OPERATIONAL"
        self.setup = DriveSetup(ratings, deceleration, latency, limits, self._reach(), config)
        self.error = None
        self.ready_at = self.clock()

    def _reach(self) -> Limits | None:
        """The most the limit objects can be set to: a flag, else the EDS's HighLimit, else
        the largest value of the object's type."""
        if self.config.limits is None:
            return None
        od = self.node.object_dictionary
        most: list[int] = []
        for index, given in zip((0x6072, 0x6073, 0x6080), self.config.reach, strict=True):
            var: Any = od[index]
            high = var.max if var.max is not None else TYPE_MAX.get(var.data_type, 2**32 - 1)
            most.append(given if given is not None else int(high))
        return Limits(*most)

    def _config_keys(self) -> list[Key]:
        """The PDO configuration (COB-ID and type of each PDO, its map) and the objects of
        ``expected_keys`` that the EDS has."""
        od = self.node.object_dictionary
        keys: list[Key] = []
        for index in (*range(0x1400, 0x1600), *range(0x1800, 0x1A00)):
            if index in od:
                keys += [(index, 1), (index, 2)]
                keys += [(index + 0x200, sub) for sub in range(9) if index + 0x200 in od]
        assert self.profile is not None  # set from the ratings first
        for index, sub in self.profile.read_back_keys():
            if index in od and (sub == 0 or sub in getattr(od[index], "subindices", {})):
                keys.append((index, sub))
        return keys

    def _read_config(self) -> dict[Key, int]:
        """Read what the bound depends on (``_config_keys``), map entries past the count
        left out."""
        out: dict[Key, int] = {}
        for index, sub in self._config_keys():
            if index & 0x200 and sub > out.get((index, 0), 0):
                continue
            out[index, sub] = self._read(index, sub)
        return out

    def _read(self, index: int, sub: int) -> int:
        var = self.node.sdo[index]
        target = var[sub] if sub or not hasattr(var, "raw") else var

        def transfer() -> int:
            return int(target.raw)

        return shared_sdo(transfer, self._pause)

    def _watch_rpdos(self, config: dict[Key, int]) -> None:
        """Frames on the drive's enabled RPDOs from others are writes of their mapped objects."""
        for comm in range(0x1400, 0x1600):
            cob = config.get((comm, 1))
            if cob is None or cob & 0x8000_0000:
                continue
            count = config.get((comm + 0x200, 0), 0)
            entries = [config.get((comm + 0x200, s), 0) for s in range(1, count + 1)]
            mapping = tuple((e >> 16, e >> 8 & 0xFF, e & 0xFF) for e in entries)

            def on_rpdo(can_id: int, data: bytearray, stamp: float, mapping: Any = mapping) -> None:
                self._seen(pdo_writes(bytes(data), mapping), stamp)

            self.network.subscribe(cob & 0x7FF, on_rpdo)

    def _seen(self, writes: list[Write], stamp: float) -> None:  # the Notifier's thread
        if writes:
            now, age = self.clock(), self._stamp_age(stamp)
            self.writes.extend((now, w, age) for w in writes)

    def _on_sdo_request(self, can_id: int, data: bytearray, stamp: float) -> None:
        self._seen(self._sdo_watch.frame(bytes(data)), stamp)

    def _on_nmt(self, can_id: int, data: bytearray, stamp: float) -> None:
        self._seen(nmt_writes(bytes(data), self.node_id), stamp)

    def _verify(self, cmd: VerifyCommand) -> None:
        """Read back what the guard asked for, the limits and the statusword."""
        keys = [*cmd.keys, STATUSWORD_KEY]
        if self.config.limits is not None:
            keys += [(i, 0) for i in self.config.limits.as_objects()]
        read: dict[Key, int | None] = {}
        for index, sub in keys:
            if index & 0x200 and 0x1600 <= index < 0x1C00 and sub > (read.get((index, 0)) or 0):
                continue  # past the map's count
            self._controlwords_first()
            try:
                read[index, sub] = self._read(index, sub)
            except (*SDO_ERRORS, KeyError):
                read[index, sub] = None
        self.verified.append((cmd.seq, read))

    def _setup_meter_node(self, counter: CounterConfig) -> None:
        """The power-meter node's TPDOs: the one that carries the counter feeds the guard."""
        meter = self.meter_node
        assert meter is not None
        maps = meter.tpdo.map
        assert maps is not None
        for pdo in maps.values():  # a meter has fewer TPDOs than the generic EDS
            with contextlib.suppress(canopen.SdoAbortedError):
                pdo.read()
        carrying = [
            pdo
            for pdo in meter.tpdo.values()
            if pdo.enabled and any(v.index == counter.index for v in pdo)
        ]
        if not carrying:
            raise SetupError(
                f"no TPDO of power-meter node {counter.node} carries 0x{counter.index:04X}"
            )
        for pdo in carrying:
            pdo.add_callback(self._on_counter_tpdo)
        meter.nmt.state = "OPERATIONAL"

    def _setup_limits(self) -> Limits | None:
        """Write the limits closed and read them back (refused: the drive cannot be guarded)."""
        if self.config.limits is None:
            return None
        closed = self.config.limits.closed()
        taken, detail = self._write_limits(closed)
        if taken is None:  # set-up is tried again
            raise canopen.SdoCommunicationError(detail)
        if not taken:
            raise SetupError(f"the drive does not take its limits: {detail}")
        return closed

    def _write_limits(self, limits: Limits) -> tuple[bool | None, str]:
        """Write each limit object, read it back; (all taken, what went wrong): None when no
        answer came through (the guard writes them again)."""
        for index, value in limits.as_objects().items():
            self._controlwords_first()
            try:
                back = self._write_read(index, value)
            except KeyError:
                return False, f"0x{index:04X} is not in the EDS {self.config.eds}"
            except canopen.SdoAbortedError as exc:
                return False, f"0x{index:04X} = {value}: {exc}"
            except (canopen.SdoCommunicationError, can.CanError) as exc:
                return None, f"0x{index:04X} = {value}: {exc}"
            if back != value:
                read = Limits(*{**limits.as_objects(), index: back}.values())
                assert self.profile is not None  # set from the ratings first
                return False, self.profile.mismatch(limits, read) or ""
        return True, ""

    def _write_read(self, index: int, value: int) -> int:
        """Write ``value`` and read it back by SDO (``shared_sdo``)."""
        sdo = self.node.sdo

        def transfer() -> int:
            sdo[index].raw = value
            return int(sdo[index].raw)

        return shared_sdo(transfer, self._pause)

    def _timed_controlword(self, controlword: int) -> int:
        """Write a controlword by SDO; the µs until the drive answered."""
        start = self.clock()
        self.node.sdo[CONTROLWORD].raw = controlword
        took = self.clock() - start
        self.latency_max_us = max(self.latency_max_us, took)
        return took

    def _disable(self) -> None:
        """Disable voltage by SDO, best effort (the drive answers SDO but cannot be guarded)."""
        try:
            self.node.sdo[CONTROLWORD].raw = CW_DISABLE_VOLTAGE
        except (canopen.SdoCommunicationError, canopen.SdoAbortedError, can.CanError, KeyError):
            self.command_failures += 1

    def _age_us(self, pdo: Any) -> int:
        """How long ago the frame was received (its timestamp is wall-clock, as python-can's)."""
        return self._stamp_age(getattr(pdo, "timestamp", None))

    @staticmethod
    def _stamp_age(stamp: float | None) -> int:
        return 0 if not stamp else max(0, round((time.time() - stamp) * 1e6))

    def _on_tpdo(self, pdo: Any) -> None:  # the Notifier's thread
        values = {var.index: int(var.raw) for var in pdo}
        counter = self.config.counter
        if counter is not None and counter.node is None and counter.index in values:
            values[COUNTER_KEY] = values.pop(counter.index)
        state = power_state(values[STATUSWORD]) if STATUSWORD in values else None
        self.samples.append((self.clock(), values, state, self._age_us(pdo)))

    def _on_counter_tpdo(self, pdo: Any) -> None:  # the Notifier's thread
        counter = self.config.counter
        assert counter is not None
        for var in pdo:
            if var.index == counter.index and var.subindex == counter.subindex:
                reading = {COUNTER_KEY: int(var.raw)}
                self.samples.append((self.clock(), reading, None, self._age_us(pdo)))

    def _execute(self, cmd: Command | LimitsCommand | VerifyCommand) -> None:
        if isinstance(cmd, VerifyCommand):
            self._verify(cmd)
            return
        if isinstance(cmd, LimitsCommand):
            self.limit_answers.append((cmd.limits, *self._write_limits(cmd.limits)))
            return
        controlword = cmd.controlword
        if controlword is None:
            controlword = enable_step(power_state(int(self.node.statusword)))
            if controlword is None:
                return
        try:
            if cmd.by_sdo or self.node.rpdo_pointers.get(CONTROLWORD) is None:
                self._timed_controlword(controlword)  # by SDO: the answer times the drive
            else:
                self.node.controlword = controlword  # by RPDO: nothing to time
        except SDO_ERRORS as exc:
            self.command_failures += 1
            log.warning("drive %d: controlword 0x%04X lost: %s", self.node_id, controlword, exc)
            return
        self.commands_sent += 1
        sent = self.clock()
        if cmd.controlword is not None:  # a stop (enabling is not a matter of safety)
            self.reaction_max_us = max(self.reaction_max_us, sent - cmd.at)
        self.last_command = {
            "controlword": controlword,
            "why": cmd.why,
            "decided_at_us": cmd.at,
            "reaction_us": sent - cmd.at,
        }

    def status(self) -> dict[str, Any]:
        return {
            "ready": self.ready_at is not None,
            "error": self.error,
            "commands_sent": self.commands_sent,
            "command_failures": self.command_failures,
            "last_command": self.last_command,
            "reaction_max_us": self.reaction_max_us,
            "latency_max_us": self.latency_max_us,
        }
