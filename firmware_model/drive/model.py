"""``DriveModel``: a CiA 402 servo drive without CAN or clock (time passed in, integer µs).

One place moves the drive: ``advance(now_us)`` runs fixed 100 µs substeps up to ``now_us`` (the
remainder waits for the next call, so the result does not depend on how time is chunked):
heartbeat consumer timeout, power state machine, current demand, motor. Every other entry point
advances first, then acts at the model's time.

Host side, without CAN::

    model = DriveModel(10)
    model.write(0x6060, 0, 3)          # profiled velocity
    model.write(0x60FF, 0, 50_000)     # 50 rad/s (unit 0.001 rad/s)
    for cw in (0x06, 0x07, 0x0F):
        model.write(0x6040, 0, cw)     # shutdown, switch on, enable operation
    model.advance(1_000_000)
    model.read(0x6041, 0), model.velocity_rad_s, model.drawn_uj

Object dictionary (``drive.eds``): SDO-style ``read``/``write`` of integer objects; live values
(statusword, actual values) are computed on read; a bad write raises ``DriveAbort`` (its SDO abort
code), is counted in ``bad_writes`` and changes nothing. Units: position 0.001 rad, velocity
0.001 rad/s, acceleration 0.001 rad/s², torque and current per mille of rated (0x6076 mNm, 0x6075
mA), DC link voltage mV (0x6079), DC link current mA (0x2010, negative when regenerating), energy
drawn µJ (0x2011, ``drawn_uj`` modulo 2**32).

Limits hold in every state: |τ| <= 0x6072 (‰ of rated torque) and kt·0x6073 (‰ of rated current),
0 meaning no torque at all; no motoring torque (τ·ω > 0) takes |ω| past 0x6080 max motor speed
(0.001 rad/s, more than 0), which also bounds the PV target; statusword bit 11 while a limit cuts
the demand. So the power drawn never exceeds τ_max·ω_max + R·i_max².

Default TPDOs (event timer 10 ms): TPDO1 0x6041, 0x6077, 0x2011; TPDO2 0x606C, 0x6064; TPDO3
0x6078, 0x6079, 0x2010. RPDO1: 0x6040.

CAN-facing, still pure: ``set_nmt`` (TPDOs and RPDOs run only in OPERATIONAL), ``receive(cob_id,
data, now_us)`` (heartbeats of the 0x1016 producer, SYNC at 0x1005, RPDO1) returns the frames
SYNC makes due, ``due_tpdos(now_us)`` the event-timer ones, ``take_emcys()`` the EMCYs to send.

Communication errors react per 0x6007 (0 none, 1 fault, 2 disable voltage, 3 quick stop): a
heartbeat consumer timeout (error code 0x8130), and NMT leaving OPERATIONAL while the drive is in
OPERATION ENABLED or QUICK STOP ACTIVE (error code 0x8100): the master stopping the node's PDOs
means it no longer hears the drive, so it is treated like a lost heartbeat.

``NodeModel`` is what any emulated node shares (object dictionary from its EDS, NMT, PDOs);
``DriveModel`` and ``power_meter.PowerMeterModel`` are two.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable

from firmware_model.drive.motor import LoadTorque, Motor, MotorParams
from firmware_model.drive.power import (
    FAULT,
    FAULT_REACTION,
    MODES,
    OPERATION_ENABLED,
    PV,
    QUICK_STOP,
    SWITCH_ON_DISABLED,
    TORQUE_STATES,
    Limits,
    PowerStateMachine,
)

__all__ = ["EDS", "SUBSTEP_US", "DriveAbort", "DriveModel", "Frame", "NodeModel"]

EDS = Path(__file__).with_name("drive.eds")
"""The emulated drive's electronic data sheet."""
SUBSTEP_US = 100
NO_SPEED_LIMIT = 10_000_000
"""0x6080 of a drive whose EDS has none (0.001 rad/s): 10,000 rad/s, as its default."""
"""Fixed integration step."""
TARGET_WINDOW_RAD_S = 0.1
"""PV target reached (statusword bit 10): |ω − target| below this, the ramp at its end."""

Frame = tuple[int, bytes]
"""A CAN frame to send: (11-bit identifier, data)."""

ABORT_READ_ONLY = 0x06010002
ABORT_NOT_IN_OD = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_SUB = 0x06090011
ABORT_RANGE = 0x06090030
ABORT_TOO_LOW = 0x06090032
ABORT_DEVICE_STATE = 0x08000022

EMCY_HEARTBEAT = 0x8130
EMCY_COMMUNICATION = 0x8100

_RANGES = {
    0x1: (0, 1),
    0x2: (-(2**7), 2**7 - 1),
    0x3: (-(2**15), 2**15 - 1),
    0x4: (-(2**31), 2**31 - 1),
    0x5: (0, 2**8 - 1),
    0x6: (0, 2**16 - 1),
    0x7: (0, 2**32 - 1),
}
_CHOICES = {
    0x6060: set(MODES),
    0x605A: {0, 1, 2, 5, 6},
    0x605E: {0, 1, 2},
    0x6007: {0, 1, 2, 3},
}
_POSITIVE = (0x6080, 0x6083, 0x6084, 0x6085)
_PDO_INVALID = 1 << 31


class DriveAbort(Exception):
    """A refused object access; ``code`` is the SDO abort code."""

    def __init__(self, code: int, what: str) -> None:
        super().__init__(f"0x{code:08X}: {what}")
        self.code = code


def _clamp(value: float, low: int, high: int) -> int:
    return max(low, min(high, round(value)))


class _Tpdo:
    """Transmission bookkeeping of one TPDO."""

    def __init__(self) -> None:
        self.next_due_us = 0
        self.last_sent_us: int | None = None
        self.last_data: bytes | None = None
        self.syncs = 0


class NodeModel:
    """A CANopen node's object dictionary, NMT state and PDOs, pure (time passed in, integer µs).

    Integer objects take their EDS defaults, then ``defaults``; a subclass computes live ones in
    ``_live``, refuses more values in ``_check``, reacts to writes in ``_written`` and runs its
    time in ``advance``. TPDOs and RPDOs are the 0x18xx and 0x14xx objects the EDS has."""

    def __init__(
        self,
        node_id: int,
        now_us: int = 0,
        *,
        defaults: Mapping[tuple[int, int], int] | None = None,
        eds: Path,
    ) -> None:
        self.node_id = node_id
        self.od = canopen.import_od(str(eds), node_id)
        self.time_us = now_us
        self.nmt = "PRE-OPERATIONAL"
        self.values = self._eds_defaults()
        self._tpdos = {i: _Tpdo() for i in self._pdo_comms(0x1800)}
        self._rpdos = self._pdo_comms(0x1400)
        for key, value in (defaults or {}).items():
            self._check(*key, value)
            self.values[key] = value
        self._defaults = dict(self.values)
        self.bad_writes = self.decode_errors = 0
        self._emcys: list[tuple[int, int]] = []
        self._rpdo_pending: list[tuple[int, int, int]] = []

    # -- object dictionary ------------------------------------------------------------------

    def _eds_defaults(self) -> dict[tuple[int, int], int]:
        out: dict[tuple[int, int], int] = {}
        for index in self.od:
            obj = self.od[index]
            subs = obj.values() if isinstance(obj, (ODRecord, ODArray)) else [obj]
            for var in subs:
                if var.data_type in _RANGES and isinstance(var.default, int):
                    out[index, var.subindex] = var.default
        return out

    def _pdo_comms(self, first: int) -> tuple[int, ...]:
        """The PDO communication objects from ``first`` on that the EDS has."""
        return tuple(i for i in range(first, first + 0x200) if i in self.od)

    def _var(self, index: int, subindex: int) -> ODVariable:
        if index not in self.od:
            raise DriveAbort(ABORT_NOT_IN_OD, f"no object 0x{index:04X}")
        obj = self.od[index]
        if isinstance(obj, ODVariable):
            return obj
        if subindex not in obj.subindices:
            raise DriveAbort(ABORT_SUB, f"no sub-index 0x{index:04X}:{subindex}")
        var = obj[subindex]
        assert isinstance(var, ODVariable)
        return var

    def serves(self, index: int, subindex: int) -> bool:
        """Whether ``read``/``write`` serve this object (strings are left to the EDS);
        ``DriveAbort`` if there is no such object."""
        return self._var(index, subindex).data_type in _RANGES

    def read(self, index: int, subindex: int = 0) -> int:
        """The object's value now (advance first to make it current)."""
        var = self._var(index, subindex)
        if var.data_type not in _RANGES:
            raise DriveAbort(ABORT_NOT_IN_OD, f"0x{index:04X} is not an integer object")
        live = self._live(index)
        return self.values[index, var.subindex] if live is None else live

    def _live(self, index: int) -> int | None:
        """The value of a live object, computed now; None for a stored one."""
        return None

    def write(self, index: int, subindex: int, value: int, now_us: int | None = None) -> None:
        """SDO-style write (after advancing to ``now_us`` if given); ``DriveAbort`` if refused."""
        if now_us is not None:
            self.advance(now_us)
        try:
            var = self._var(index, subindex)
            if not var.writable:
                raise DriveAbort(ABORT_READ_ONLY, f"0x{index:04X}:{subindex} is read-only")
            self._check(index, var.subindex, value)
        except DriveAbort:
            self.bad_writes += 1
            raise
        self.values[index, var.subindex] = value
        self._written(index, var.subindex, value)

    def _check(self, index: int, sub: int, value: int) -> None:
        """Refuse a value the object cannot take (nothing changes)."""
        var = self._var(index, sub)
        if var.data_type not in _RANGES:
            raise DriveAbort(ABORT_READ_ONLY, f"0x{index:04X} is not an integer object")
        low, high = _RANGES[var.data_type]
        if not low <= value <= high:
            raise DriveAbort(ABORT_RANGE, f"{value} outside {low}..{high}")
        if index == 0x1005 and value & ~0x7FF:
            raise DriveAbort(ABORT_RANGE, "SYNC COB-ID: 11-bit consumer only")
        if index in (*self._tpdos, *self._rpdos):
            self._check_comm(index, sub, value)
        if index - 0x200 in (*self._tpdos, *self._rpdos):
            self._check_mapping(index, sub, value)

    def _check_comm(self, index: int, sub: int, value: int) -> None:
        if sub == 1:
            old = self.values[index, 1]
            if value & 0x3FFFF800 or not value & 0x7FF:
                raise DriveAbort(ABORT_RANGE, "PDO COB-ID: 11-bit, not 0")
            if not (old | value) & _PDO_INVALID and (old ^ value) & 0x7FF:
                raise DriveAbort(ABORT_RANGE, "set bit 31 (PDO invalid) before changing a COB-ID")
        elif sub == 2 and 240 < value < 254:
            raise DriveAbort(ABORT_RANGE, "transmission type: 0-240, 254 or 255")

    def _check_mapping(self, index: int, sub: int, value: int) -> None:
        entries = [self.values[index, s] for s in range(1, 256) if (index, s) in self.values]
        if sub == 0:
            if value > len(entries):
                raise DriveAbort(ABORT_RANGE, f"at most {len(entries)} mapped objects")
            bits = sum(self._mapped_bits(index, e) for e in entries[:value])
            if bits > 64:
                raise DriveAbort(ABORT_PDO_LENGTH, f"{bits} bits do not fit in a PDO")
        else:
            if self.values[index, 0] != 0:
                raise DriveAbort(ABORT_DEVICE_STATE, "set the number of mapped objects to 0 first")
            if value:
                self._mapped_bits(index, value)

    def _mapped_bits(self, map_index: int, entry: int) -> int:
        """The length of a mapping entry; ``DriveAbort`` if the object cannot be mapped so."""
        index, sub, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
        try:
            var = self._var(index, sub)
        except DriveAbort:
            raise DriveAbort(ABORT_NOT_MAPPABLE, f"0x{entry:08X}: no such object") from None
        receive = map_index < 0x1A00
        if (
            not var.pdo_mappable
            or var.data_type not in _RANGES
            or bits != len(var)
            or not (var.writable if receive else var.readable)
        ):
            raise DriveAbort(ABORT_NOT_MAPPABLE, f"0x{entry:08X} cannot be mapped here")
        return bits

    def _written(self, index: int, sub: int, value: int) -> None:
        """What a successful write does beyond storing the value."""
        if index in self._tpdos:
            self._restart_tpdo(index, self.time_us)

    def _restart_tpdo(self, comm: int, now_us: int) -> None:
        self._tpdos[comm] = _Tpdo()
        self._tpdos[comm].next_due_us = now_us

    # -- time, NMT, EMCY ----------------------------------------------------------------------

    def advance(self, now_us: int) -> None:
        """Bring the node to ``now_us`` (earlier times are ignored)."""
        self.time_us = max(self.time_us, now_us)

    def set_nmt(self, state: str, now_us: int) -> None:
        """The NMT state changed (python-canopen's names); TPDO timers restart in OPERATIONAL."""
        self.advance(now_us)
        old, self.nmt = self.nmt, state
        if state == "OPERATIONAL" and old != state:
            for comm in self._tpdos:
                self._restart_tpdo(comm, now_us)

    def reset(self, application: bool, now_us: int) -> None:
        """NMT reset communication (1000h-1FFFh back to defaults) or reset node (every object)."""
        self.advance(now_us)
        for key, value in self._defaults.items():
            if application or key[0] < 0x2000:
                self.values[key] = value
        self.nmt = "PRE-OPERATIONAL"

    def take_emcys(self) -> list[tuple[int, int]]:
        """EMCYs to send, ``(error code, error register)``; 0 is an error reset."""
        out, self._emcys = self._emcys, []
        return out

    # -- PDOs ---------------------------------------------------------------------------------

    def _pdo_entries(self, comm: int) -> list[tuple[int, int, int]]:
        """``(index, subindex, bits)`` mapped by the PDO whose communication object is ``comm``."""
        mapping = comm + 0x200
        count = self.values[mapping, 0]
        entries = [self.values[mapping, s] for s in range(1, count + 1)]
        return [(e >> 16, (e >> 8) & 0xFF, e & 0xFF) for e in entries]

    def tpdo_values(self) -> dict[int, int]:
        """Every object mapped in a valid TPDO, sampled now: ``{index: value}``."""
        out: dict[int, int] = {}
        for comm in self._tpdos:
            if not self.values[comm, 1] & _PDO_INVALID:
                for index, sub, _ in self._pdo_entries(comm):
                    out[index] = self.read(index, sub)
        return out

    def _tpdo_frame(self, comm: int) -> Frame:
        data = bytearray()
        for index, sub, bits in self._pdo_entries(comm):
            signed = self._var(index, sub).data_type in (0x2, 0x3, 0x4)
            data += self.read(index, sub).to_bytes(bits // 8, "little", signed=signed)
        return self.values[comm, 1] & 0x7FF, bytes(data)

    def due_tpdos(self, now_us: int) -> list[Frame]:
        """The event-driven TPDOs (types 254/255) due at ``now_us``, all sampled at one time:
        every event timer period, or with the timer 0 when a value changed (at most once per
        inhibit time, and per ms)."""
        self.advance(now_us)
        if self.nmt != "OPERATIONAL":
            return []
        frames = []
        for comm, run in self._tpdos.items():
            if self.values[comm, 1] & _PDO_INVALID or self.values[comm, 2] < 254:
                continue
            frame = self._tpdo_frame(comm)
            if not self._tpdo_due(comm, run, frame[1], now_us):
                continue
            run.last_sent_us, run.last_data = now_us, frame[1]
            frames.append(frame)
        return frames

    def _tpdo_due(self, comm: int, run: _Tpdo, data: bytes, now_us: int) -> bool:
        """Whether an event-driven TPDO goes now (its period restarts when it does)."""
        period_us = self.values.get((comm, 5), 0) * 1000
        if period_us:
            if now_us < run.next_due_us:
                return False
            run.next_due_us += period_us
            if run.next_due_us <= now_us:  # fell behind: restart the period from now
                run.next_due_us = now_us + period_us
            return True
        gap_us = max(self.values.get((comm, 3), 0) * 100, 1000)
        recent = run.last_sent_us is not None and now_us - run.last_sent_us < gap_us
        return data != run.last_data and not recent

    def receive(self, cob_id: int, data: bytes, now_us: int) -> list[Frame]:
        """A frame from the bus: SYNC or RPDO; returns the TPDOs SYNC makes due."""
        self.advance(now_us)
        if self.nmt != "OPERATIONAL":
            return []
        if (0x1005, 0) in self.values and cob_id == self.values[0x1005, 0] & 0x7FF:
            return self._sync()
        for comm in self._rpdos:
            if not self.values[comm, 1] & _PDO_INVALID and cob_id == self.values[comm, 1] & 0x7FF:
                self._rpdo(comm, data)
        return []

    def _rpdo(self, comm: int, data: bytes) -> None:
        entries = self._pdo_entries(comm)
        if len(data) < sum(bits for _, _, bits in entries) // 8:
            self.decode_errors += 1
            return
        offset, values = 0, []
        for index, sub, bits in entries:
            signed = self._var(index, sub).data_type in (0x2, 0x3, 0x4)
            raw = data[offset : offset + bits // 8]
            values.append((index, sub, int.from_bytes(raw, "little", signed=signed)))
            offset += bits // 8
        if self.values[comm, 2] <= 240:
            self._rpdo_pending = values  # synchronous: applied at the next SYNC
        else:
            self._apply(values)

    def _apply(self, values: list[tuple[int, int, int]]) -> None:
        for index, sub, value in values:
            with contextlib.suppress(DriveAbort):  # counted in bad_writes
                self.write(index, sub, value)

    def _sync(self) -> list[Frame]:
        pending, self._rpdo_pending = self._rpdo_pending, []
        self._apply(pending)
        frames = []
        for comm, run in self._tpdos.items():
            kind = self.values[comm, 2]
            if self.values[comm, 1] & _PDO_INVALID or kind > 240:
                continue
            frame = self._tpdo_frame(comm)
            run.syncs += 1
            if (kind == 0 and frame[1] != run.last_data) or (kind and run.syncs >= kind):
                run.syncs, run.last_data, run.last_sent_us = 0, frame[1], self.time_us
                frames.append(frame)
        return frames

    def status(self) -> dict[str, Any]:
        """What every node's status file shows."""
        return {
            "node": self.node_id,
            "nmt": self.nmt,
            "time_us": self.time_us,
            "bad_writes": self.bad_writes,
            "decode_errors": self.decode_errors,
        }


class DriveModel(NodeModel):
    """State machine, motor and object dictionary values of one drive (see the module doc)."""

    def __init__(
        self,
        node_id: int,
        now_us: int = 0,
        *,
        params: MotorParams | None = None,
        load: LoadTorque | None = None,
        defaults: Mapping[tuple[int, int], int] | None = None,
        eds: Path = EDS,
    ) -> None:
        super().__init__(node_id, now_us, defaults=defaults, eds=eds)
        self.motor = Motor(params or MotorParams(), load or LoadTorque())
        self.start_us = now_us
        self.psm = PowerStateMachine(changed_us=now_us)
        self.faults = self.heartbeat_timeouts = self.comm_errors = 0
        self.error_code = 0
        self.fault_reason = ""
        self.heartbeat_active = False
        self.heartbeat_last_us = 0
        self._limits = self._make_limits()

    # -- object dictionary ------------------------------------------------------------------

    def _live(self, index: int) -> int | None:
        m, p = self.motor, self.motor.params
        if index == 0x6041:
            return self.psm.statusword(self._target_reached())
        if index == 0x6061:
            return self.values[0x6060, 0]
        if index == 0x6064:
            return (round(m.theta * 1000) + 2**31) % 2**32 - 2**31  # wraps like an encoder
        if index == 0x606C:
            return _clamp(m.omega * 1000, -(2**31), 2**31 - 1)
        if index == 0x6077:
            return _clamp(m.torque / p.rated_torque * 1000, -(2**15), 2**15 - 1)
        if index == 0x6078:
            return _clamp(m.current / p.rated_current * 1000, -(2**15), 2**15 - 1)
        if index == 0x6079:
            return _clamp(p.dc_voltage * 1000, 0, 2**32 - 1)
        if index == 0x2010:
            return _clamp(m.power_w / p.dc_voltage * 1000, -(2**15), 2**15 - 1)
        if index == 0x2011:
            return self.drawn_uj % 2**32
        if index == 0x6075:
            return _clamp(p.rated_current * 1000, 0, 2**32 - 1)
        if index == 0x6076:
            return _clamp(p.rated_torque * 1000, 0, 2**32 - 1)
        if index == 0x603F:
            return self.error_code
        if index == 0x1001:
            faulted = self.psm.state in (FAULT, FAULT_REACTION)
            communication = faulted and self.error_code & 0xFF00 == 0x8100
            return int(faulted) | (0x10 if communication else 0)
        return None

    def _target_reached(self) -> bool:
        s, lim = self.psm, self._limits
        if s.state == QUICK_STOP:
            return s.stopped
        if s.state != OPERATION_ENABLED or lim.mode != PV:
            return False
        return (
            s.reference == lim.target_velocity
            and abs(self.motor.omega - lim.target_velocity) < TARGET_WINDOW_RAD_S
        )

    def _check(self, index: int, sub: int, value: int) -> None:
        super()._check(index, sub, value)
        if index in _CHOICES and value not in _CHOICES[index]:
            raise DriveAbort(ABORT_RANGE, f"0x{index:04X} does not support {value}")
        if index in _POSITIVE and value == 0:
            raise DriveAbort(ABORT_TOO_LOW, f"0x{index:04X} must be more than 0")
        if index == 0x1016 and sub == 1 and value >> 23:
            raise DriveAbort(ABORT_RANGE, "consumer heartbeat: node id 1-127, bits 23-31 clear")

    def _written(self, index: int, sub: int, value: int) -> None:
        super()._written(index, sub, value)
        self._limits = self._make_limits()
        now = self.time_us
        if index == 0x6040:
            was_fault = self.psm.state == FAULT
            self.psm.controlword(value, self.motor.omega, self._limits, now)
            if was_fault and self.psm.state != FAULT:
                self.error_code = 0
                self._emcys.append((0, 0))  # error reset
        elif index == 0x6060:  # bumpless mode change
            self.psm.reference = self.motor.omega
            self.psm.pi.integral = self.motor.torque
        elif index == 0x1016:
            self.heartbeat_active = False  # re-armed by the producer's next heartbeat

    def _make_limits(self) -> Limits:
        v, p = self.values, self.motor.params
        max_speed = v.get((0x6080, 0), NO_SPEED_LIMIT) / 1000  # an EDS may lack the object
        return Limits(
            mode=v[0x6060, 0],
            target_velocity=max(-max_speed, min(max_speed, v[0x60FF, 0] / 1000)),
            target_torque=v[0x6071, 0] / 1000 * p.rated_torque,
            accel=v[0x6083, 0] / 1000,
            decel=v[0x6084, 0] / 1000,
            quick_stop_decel=v[0x6085, 0] / 1000,
            max_torque=min(
                v[0x6072, 0] / 1000 * p.rated_torque,
                v[0x6073, 0] / 1000 * p.rated_current * p.kt,
            ),
            max_speed=max_speed,
            quick_stop_option=v[0x605A, 0],
            fault_reaction_option=v[0x605E, 0],
        )

    # -- time ---------------------------------------------------------------------------------

    def advance(self, now_us: int) -> None:
        """Run every whole substep up to ``now_us`` (earlier times are ignored)."""
        dt = SUBSTEP_US / 1e6
        kt = self.motor.params.kt
        while self.time_us + SUBSTEP_US <= now_us:
            t = self.time_us
            t_s = (t - self.start_us) / 1e6
            self.psm.start(t)
            self._check_heartbeat(t)
            tau = self._bounded(self.psm.demand(self.motor.omega, self._limits, dt, t), dt, t_s)
            self.motor.step(dt, tau / kt, t_s)
            self.time_us = t + SUBSTEP_US

    def _bounded(self, tau: float, dt: float, t_s: float) -> float:
        """``tau`` within 0x6072/0x6073 and without motoring past 0x6080, whatever asked for it
        (statusword bit 11 when it was cut)."""
        lim = self._limits
        torque = max(-lim.max_torque, min(lim.max_torque, tau))
        out = self.motor.speed_limited(torque, dt, t_s, lim.max_speed)
        if out != tau:
            self.psm.limited = True
        return out

    def host_heartbeat(self, producer: int, now_us: int) -> None:
        """A heartbeat (or boot-up) of node ``producer`` arrived at ``now_us``."""
        self.advance(now_us)
        entry = self.values[0x1016, 1]
        if entry & 0xFFFF and (entry >> 16) & 0x7F == producer:
            self.heartbeat_active, self.heartbeat_last_us = True, now_us

    def _check_heartbeat(self, t: int) -> None:
        limit_us = (self.values[0x1016, 1] & 0xFFFF) * 1000
        if self.heartbeat_active and limit_us and t - self.heartbeat_last_us > limit_us:
            self.heartbeat_active = False  # until the producer is heard again
            self.heartbeat_timeouts += 1
            self._comm_error("heartbeat consumer timeout", EMCY_HEARTBEAT, t)

    def _comm_error(self, reason: str, code: int, t: int) -> None:
        """React per 0x6007 abort connection option code."""
        self.comm_errors += 1
        option, s = self.values[0x6007, 0], self.psm
        if option == 1:
            self.fault(reason, code, t)
        elif option == 2 and s.state not in (FAULT, FAULT_REACTION):
            s.go(SWITCH_ON_DISABLED, t)
        elif option == 3 and s.state == OPERATION_ENABLED:
            s.begin_stop(QUICK_STOP, self.motor.omega, t)
        elif option == 3 and s.state not in (FAULT, FAULT_REACTION, QUICK_STOP):
            s.go(SWITCH_ON_DISABLED, t)

    def fault(self, reason: str, code: int, t: int | None = None) -> None:
        """Enter FAULT REACTION ACTIVE with error ``code`` (EMCY queued); ignored while faulted."""
        if self.psm.state in (FAULT, FAULT_REACTION):
            return
        self.faults += 1
        self.fault_reason, self.error_code = reason, code
        self.psm.fault(self.motor.omega, self.time_us if t is None else t)
        self._emcys.append((code, self.read(0x1001)))

    # -- NMT and frames -----------------------------------------------------------------------

    def set_nmt(self, state: str, now_us: int) -> None:
        """The NMT state changed (python-canopen's names)."""
        old = self.nmt
        super().set_nmt(state, now_us)
        if old == "OPERATIONAL" and state != "OPERATIONAL" and self.psm.state in TORQUE_STATES:
            self._comm_error(f"NMT {state} while enabled", EMCY_COMMUNICATION, self.time_us)

    def reset(self, application: bool, now_us: int) -> None:
        """NMT reset communication (1000h-1FFFh back to defaults), or reset node (everything
        but the motor and the energy accounts: the drive restarts disabled, the motor coasts)."""
        super().reset(application, now_us)
        if application:
            self.psm = PowerStateMachine(changed_us=self.time_us, history=self.psm.history)
            self.error_code = 0
        self.heartbeat_active = False
        self._limits = self._make_limits()

    def receive(self, cob_id: int, data: bytes, now_us: int) -> list[Frame]:
        """A frame from the bus: heartbeat, SYNC or RPDO; returns the TPDOs SYNC makes due."""
        self.advance(now_us)
        producer = (self.values[0x1016, 1] >> 16) & 0x7F
        if producer and cob_id == 0x700 + producer:
            if len(data) == 1:
                self.host_heartbeat(producer, now_us)
            else:
                self.decode_errors += 1
        return super().receive(cob_id, data, now_us)

    # -- figures ------------------------------------------------------------------------------

    @property
    def state(self) -> str:
        """Power state (python-canopen's ``State402.SW_MASK`` names)."""
        return self.psm.state

    @property
    def mode(self) -> int:
        return self.values[0x6060, 0]

    @property
    def velocity_rad_s(self) -> float:
        return self.motor.omega

    @property
    def drawn_uj(self) -> int:
        """Electrical energy drawn from the DC link, ∫max(P, 0) dt, floor µJ."""
        return self.motor.energy.drawn.uj

    @property
    def regenerated_uj(self) -> int:
        return self.motor.energy.regenerated.uj

    @property
    def peak_power_w(self) -> float:
        return self.motor.peak_power_w

    def status(self) -> dict[str, Any]:
        """Everything worth a status file (times in the caller's µs)."""
        e, s = self.motor.energy, self.psm
        return {
            **super().status(),
            "state": s.state,
            "mode": MODES.get(self.mode, str(self.mode)),
            "velocity_rad_s": self.motor.omega,
            "position_rad": self.motor.theta,
            "current_a": self.motor.current,
            "torque_nm": self.motor.torque,
            "power_w": self.motor.power_w,
            "drawn_uj": e.drawn.uj,
            "regenerated_uj": e.regenerated.uj,
            "copper_loss_uj": e.copper_loss.uj,
            "mechanical_work_uj": math.floor(e.mechanical_work_j * 1e6),
            "friction_uj": e.friction.uj,
            "load_work_uj": math.floor(e.load_work_j * 1e6),
            "kinetic_uj": math.floor(self.motor.kinetic_j * 1e6),
            "peak_power_w": self.motor.peak_power_w,
            "statusword": self.read(0x6041),
            "error_code": self.error_code,
            "faults": self.faults,
            "fault_reason": self.fault_reason,
            "heartbeat_timeouts": self.heartbeat_timeouts,
            "communication_errors": self.comm_errors,
            "quick_stop_count": s.quick_stops,
            "stopped_at_us": s.stopped_at_us,
            "state_changed_us": s.changed_us,
            "history": [{"time_us": t, "state": name} for t, name in s.history],
        }

    def __repr__(self) -> str:
        return f"<DriveModel node {self.node_id} {self.state} ω={self.motor.omega:.3f} rad/s>"
