"""The C client library (firmware/) seen from Python: build, ctypes mirror, adapters.

``library()`` runs ``make`` in ``firmware/`` once per process and loads the shared object: the
UBSan build in-process (any report aborts the interpreter, so it cannot pass unnoticed), or the
ASan+UBSan build when ``CANERGY_C_SANITIZER=asan`` (tests/test_c_asan.py re-runs the C-vs-Python
tests that way in a child pytest with libasan preloaded). A missing compiler fails loudly.

The ctypes structures mirror ``firmware/include/canergy/*.h``; tests/test_c_binding.py checks
every field's offset and every struct's size against what the compiler laid out, so the mirror
cannot silently drift. ``CClient`` is the C client behind the interface of ``canergy.core.Client``
that the harness and the state machines use, and ``c_view`` puts a Python ``ClientState`` into
the C library's terms (counters modulo 2**32, energy in the record's units).
"""

from __future__ import annotations

import ctypes
import functools
import os
import shutil
import subprocess
from ctypes import (
    POINTER,
    Structure,
    c_bool,
    c_char_p,
    c_int,
    c_long,
    c_size_t,
    c_uint8,
    c_uint16,
    c_uint32,
    c_uint64,
    c_void_p,
)
from pathlib import Path
from typing import Any

import pytest

from canergy.codec import DEFAULT_ID_BASE, Codec, DecodeErrorReason
from canergy.core import (
    Action,
    ClientAborted,
    ClientCommitted,
    Credited,
    IntentionRefused,
    Persist,
    ReturnAcknowledged,
    Send,
    Timing,
)
from canergy.core.errors import LocalProtocolError
from canergy.core.state import ClientState, Outcome, Phase
from canergy.messages import Message, ToClient

FIRMWARE = Path(__file__).resolve().parents[2] / "firmware"
BUILD = FIRMWARE / "build"
U32 = 0xFFFF_FFFF
NEVER = 2**64 - 1
SANITIZER = os.environ.get("CANERGY_C_SANITIZER", "ubsan")

# -- the ctypes mirror of the headers ---------------------------------------------------------


class Record(Structure):
    _fields_ = [
        ("spent_uj", c_uint64),
        ("usable_uj", c_uint32),
        ("credited_mj", c_uint32),
        ("last_tx", c_uint32),
        ("return_seq", c_uint32),
        ("return_pending_uj", c_uint32),
        ("outcome", c_uint8),
        ("flags", c_uint8),
    ]


class CClientState(Structure):
    _fields_ = [
        ("rec", Record),
        ("deadline", c_uint64),
        ("return_deadline", c_uint64),
        ("id_base", c_uint32),
        ("command_timeout_us", c_uint32),
        ("return_retry_us", c_uint32),
        ("held_tx", c_uint32),
        ("nv_counter", c_uint32),
        ("held_amount_mj", c_uint16),
        ("nonce", c_uint16),
        ("node", c_uint8),
        ("phase", c_uint8),
        ("nv_slot", c_uint8),
        ("rules", c_uint8),
        ("window", c_uint16),
    ]


class Frame(Structure):
    _fields_ = [("id", c_uint32), ("dlc", c_uint8), ("data", c_uint8 * 8)]


OUT_FRAMES = 4
SLOT = 40


class Out(Structure):
    _fields_ = [
        ("frames", Frame * OUT_FRAMES),
        ("nv_image", c_uint8 * SLOT),
        ("nv_counter", c_uint32),
        ("events", c_uint16),
        ("frame_count", c_uint8),
        ("persist", c_uint8),
        ("nv_slot", c_uint8),
    ]

    def sent(self) -> list[tuple[int, bytes]]:
        return [(f.id, bytes(f.data[: f.dlc])) for f in list(self.frames)[: self.frame_count]]


class Msg(Structure):
    _fields_ = [
        ("delivered_mj", c_uint32),
        ("level_mj", c_uint32),
        ("tx", c_uint16),
        ("seq", c_uint16),
        ("nonce", c_uint16),
        ("amount_mj", c_uint16),
        ("type", c_uint8),
        ("node", c_uint8),
        ("flags", c_uint8),
        ("witness", c_uint8),
    ]


class CSession(Structure):
    _fields_ = [
        ("delivered_uj", c_uint64),
        ("returned_uj", c_uint64),
        ("deadline", c_uint64),
        ("tx", c_uint32),
        ("returns_credited", c_uint32),
        ("reserved_uj", c_uint32),
        ("resume_from", c_uint32),
        ("resume_to", c_uint32),
        ("resume_nonce", c_uint32),
        ("witness", ctypes.c_int32),
        ("sync_nonce", c_uint16),
        ("node", c_uint8),
        ("phase", c_uint8),
        ("decision", c_uint8),
        ("tries", c_uint8),
    ]


class SessionStep(Structure):
    _fields_ = [
        ("msg", Msg),
        ("credit_uj", ctypes.c_int64),
        ("send", c_uint8),
        ("resolved", c_uint8),
        ("acknowledged", c_uint8),
        ("admitted", c_uint8),
    ]


class SessionTiming(Structure):
    _fields_ = [
        ("response_timeout_us", c_uint32),
        ("retries", c_uint8),
        ("rules", c_uint8),
        ("window", c_uint16),
    ]


SUPERVISOR_NODES = 16
"""CANERGY_SUPERVISOR_NODES as the library is built."""
SUPERVISOR_SLOT = 40 + 44 * SUPERVISOR_NODES
"""CANERGY_SUPERVISOR_SLOT_SIZE: one of the two slots of the supervisor's NV image."""


class CSupervisor(Structure):
    _fields_ = [
        ("usable_uj", ctypes.c_int64),
        ("injected_uj", c_uint64),
        ("withdrawn_uj", c_uint64),
        ("sessions", CSession * SUPERVISOR_NODES),
        ("timing", SessionTiming),
        ("id_base", c_uint32),
        ("start_without", c_uint32 * 4),
        ("count", c_uint8),
    ]


class CGateway(Structure):
    _fields_ = [("up", CClientState), ("down", CSupervisor)]


class SupervisorConfig(Structure):
    _fields_ = [("id_base", c_uint32), ("timing", SessionTiming)]


class SupervisorEvent(Structure):
    _fields_ = [
        ("tx", c_uint32),
        ("amount_uj", c_uint32),
        ("node", c_uint8),
        ("resolved", c_uint8),
        ("flags", c_uint8),
    ]


class SupervisorOut(Structure):
    _fields_ = [
        ("frames", Frame * SUPERVISOR_NODES),
        ("events", SupervisorEvent * SUPERVISOR_NODES),
        ("frame_count", c_uint8),
        ("event_count", c_uint8),
        ("persist", c_uint8),
    ]


class RxFrame(Structure):
    _fields_ = [
        ("id", c_uint32),
        ("data", c_void_p),
        ("len", c_size_t),
        ("extended", c_bool),
        ("remote", c_bool),
    ]


class ClientConfig(Structure):
    _fields_ = [
        ("id_base", c_uint32),
        ("command_timeout_us", c_uint32),
        ("return_retry_us", c_uint32),
        ("node", c_uint8),
        ("rules", c_uint8),
        ("window", c_uint16),
    ]


class NvState(Structure):
    _fields_ = [
        ("record", Record),
        ("counter", c_uint32),
        ("newest_slot", c_uint8),
        ("books", c_bool),
        ("fallbacks", c_uint8),
    ]


class NodeConfig(Structure):
    _fields_ = [
        ("client", ClientConfig),
        ("telemetry_period_us", c_uint32),
        ("low_water_uj", c_uint32),
        ("return_above_uj", c_uint32),
    ]


class CNodeState(Structure):
    _fields_ = [
        ("client", CClientState),
        ("next_telemetry", c_uint64),
        ("telemetry_period_us", c_uint32),
        ("low_water_uj", c_uint32),
        ("return_above_uj", c_uint32),
        ("decode_errors", c_uint32),
        ("overflow_refused", c_uint32),
        ("was_low", c_bool),
        ("halted", c_bool),
        ("witness", c_uint8),
        ("joined", c_bool),
        ("join_nonce", c_uint16),
        ("witness_reported", c_uint8),
        ("released_uj", c_uint32),
    ]


MIRROR: dict[str, type[Structure]] = {
    "canergy_record": Record,
    "canergy_client": CClientState,
    "canergy_frame": Frame,
    "canergy_out": Out,
    "canergy_msg": Msg,
    "canergy_rx_frame": RxFrame,
    "canergy_client_config": ClientConfig,
    "canergy_nv_state": NvState,
    "canergy_node_config": NodeConfig,
    "canergy_node": CNodeState,
    "canergy_session": CSession,
    "canergy_session_step": SessionStep,
    "canergy_session_timing": SessionTiming,
    "canergy_supervisor": CSupervisor,
    "canergy_supervisor_config": SupervisorConfig,
    "canergy_supervisor_out": SupervisorOut,
    "canergy_supervisor_event": SupervisorEvent,
    "canergy_gateway": CGateway,
}

# Constants of the headers the tests use.
OK, ERR_ARGUMENT, ERR_PHASE, ERR_AMOUNT, ERR_END = 0, -1, -2, -3, -5
ERR_WINDOW, ERR_UNCONFIRMED = -6, -7
RX_OTHER_NODE = 16
EV_COMMITTED, EV_TIMEOUT_COMMIT, EV_ABORTED, EV_CREDITED = 0x01, 0x02, 0x04, 0x08
EV_RETURN_ACKED, EV_REFUSED, EV_ADMITTED, EV_RELEASED = 0x10, 0x20, 0x40, 0x80
PHASES = {
    Phase.IDLE: 0,
    Phase.AWAIT_COMMAND: 1,
    Phase.JOINING: 2,
    Phase.RESUMING: 3,
    Phase.SYNCING: 4,
}
RULES = {"hardened": 0, "witnessed": 1}
"""enum canergy_rules: the rule sets the C client runs."""
FLAG_CREDITED_UNKNOWN, FLAG_PENDING_DRAW = 0x01, 0x02
DIRECTIONS = {None: 0, "to_client": 1, "to_supervisor": 2}
REASONS = {i + 1: reason for i, reason in enumerate(DecodeErrorReason)}
"""C decode status -> Python reason: the C enum lists them in the same order."""

_SIGNATURES: dict[str, tuple[Any, list[Any]]] = {
    "canergy_test_offset": (c_long, [c_char_p]),
    "canergy_test_sizeof": (c_long, [c_char_p]),
    "canergy_id_base_valid": (c_bool, [c_uint32]),
    "canergy_session_init": (None, [POINTER(CSession), c_uint8]),
    "canergy_session_begin": (
        c_int,
        [POINTER(CSession), POINTER(SessionTiming), c_uint32, c_uint64, POINTER(SessionStep)],
    ),
    "canergy_session_decide": (
        c_int,
        [POINTER(CSession), POINTER(SessionTiming), c_bool, c_uint64, POINTER(SessionStep)],
    ),
    "canergy_session_on_msg": (
        None,
        [POINTER(CSession), POINTER(SessionTiming), POINTER(Msg), c_uint64, POINTER(SessionStep)],
    ),
    "canergy_session_timer": (
        None,
        [POINTER(CSession), POINTER(SessionTiming), c_uint64, POINTER(SessionStep)],
    ),
    "canergy_session_restart": (None, [POINTER(CSession), c_uint64, POINTER(SessionStep)]),
    "canergy_session_start": (
        None,
        [POINTER(CSession), POINTER(SessionTiming), c_uint16, c_uint64, POINTER(SessionStep)],
    ),
    "canergy_supervisor_init": (
        c_int,
        [POINTER(CSupervisor), POINTER(SupervisorConfig), c_void_p, c_uint8, c_uint64],
    ),
    "canergy_supervisor_begin": (
        c_int,
        [POINTER(CSupervisor), c_uint8, c_uint32, c_uint64, POINTER(SupervisorOut)],
    ),
    "canergy_supervisor_decide": (
        c_int,
        [POINTER(CSupervisor), c_uint8, c_bool, c_uint64, POINTER(SupervisorOut)],
    ),
    "canergy_supervisor_on_frame": (
        c_int,
        [POINTER(CSupervisor), POINTER(RxFrame), c_uint64, POINTER(SupervisorOut)],
    ),
    "canergy_supervisor_on_timer": (None, [POINTER(CSupervisor), c_uint64, POINTER(SupervisorOut)]),
    "canergy_supervisor_deadline": (c_uint64, [POINTER(CSupervisor)]),
    "canergy_supervisor_restart": (None, [POINTER(CSupervisor), c_uint64]),
    "canergy_supervisor_start": (
        None,
        [POINTER(CSupervisor), c_uint16, c_uint64, POINTER(SupervisorOut)],
    ),
    "canergy_supervisor_start_without": (c_int, [POINTER(CSupervisor), c_uint8]),
    "canergy_supervisor_unconfirmed": (c_uint8, [POINTER(CSupervisor), c_void_p]),
    "canergy_supervisor_inject": (c_int, [POINTER(CSupervisor), c_uint64]),
    "canergy_supervisor_withdraw": (c_int, [POINTER(CSupervisor), c_uint64]),
    "canergy_gateway_forward": (c_uint32, [POINTER(CGateway), POINTER(Out)]),
    "canergy_gateway_on_up_frame": (
        c_int,
        [POINTER(CGateway), POINTER(RxFrame), c_uint64, POINTER(Out)],
    ),
    "canergy_gateway_on_up_timer": (None, [POINTER(CGateway), c_uint64, POINTER(Out)]),
    "canergy_gateway_give_back": (c_int, [POINTER(CGateway), c_uint32, c_uint64, POINTER(Out)]),
    "canergy_gateway_link_gap": (ctypes.c_int64, [POINTER(CGateway)]),
    "canergy_gateway_upstream_waiting": (ctypes.c_bool, [POINTER(CGateway)]),
    "canergy_gateway_begin": (
        c_int,
        [POINTER(CGateway), c_uint8, c_uint32, c_uint64, POINTER(SupervisorOut)],
    ),
    "canergy_supervisor_image": (c_size_t, [POINTER(CSupervisor), c_uint32, c_void_p]),
    "canergy_supervisor_load": (
        c_int,
        [
            POINTER(CSupervisor),
            POINTER(SupervisorConfig),
            c_void_p,
            c_uint8,
            c_uint64,
            c_void_p,
            c_size_t,
            POINTER(c_uint32),
            POINTER(c_uint8),
        ],
    ),
    "canergy_encode": (c_int, [c_uint32, POINTER(Msg), POINTER(Frame)]),
    "canergy_decode": (c_int, [c_uint32, POINTER(RxFrame), c_int, POINTER(Msg)]),
    "canergy_crc8": (c_uint8, [c_uint8, c_void_p, c_size_t]),
    "canergy_crc32": (c_uint32, [c_uint32, c_void_p, c_size_t]),
    "canergy_record_pack": (None, [POINTER(Record), c_void_p]),
    "canergy_record_unpack": (c_int, [c_void_p, POINTER(Record)]),
    "canergy_nv_slot_encode": (None, [c_uint32, c_void_p, c_size_t, c_void_p]),
    "canergy_nv_load": (None, [c_void_p, c_size_t, POINTER(NvState)]),
    "canergy_client_start": (
        c_int,
        [
            POINTER(CClientState),
            POINTER(ClientConfig),
            c_void_p,
            c_size_t,
            c_uint16,
            c_uint64,
            POINTER(Out),
        ],
    ),
    "canergy_client_on_frame": (
        c_int,
        [POINTER(CClientState), POINTER(RxFrame), c_uint64, POINTER(Out)],
    ),
    "canergy_client_on_timer": (None, [POINTER(CClientState), c_uint64, POINTER(Out)]),
    "canergy_client_command_timer": (None, [POINTER(CClientState), c_uint64, POINTER(Out)]),
    "canergy_client_return_timer": (None, [POINTER(CClientState), c_uint64, POINTER(Out)]),
    "canergy_client_deadline": (c_uint64, [POINTER(CClientState)]),
    "canergy_client_spend": (c_int, [POINTER(CClientState), c_uint32, POINTER(Out)]),
    "canergy_client_draw": (c_int, [POINTER(CClientState), c_uint32, c_uint64, POINTER(Out)]),
    "canergy_client_can_draw": (c_bool, [POINTER(CClientState)]),
    "canergy_client_resume": (
        None,
        [POINTER(CClientState), c_uint16, c_uint64, POINTER(Out)],
    ),
    "canergy_client_give_back": (c_int, [POINTER(CClientState), c_uint32, c_uint64, POINTER(Out)]),
    "canergy_client_can_give_back": (c_bool, [POINTER(CClientState)]),
    "canergy_client_joining": (c_bool, [POINTER(CClientState)]),
    "canergy_client_restart": (None, [POINTER(CClientState), c_uint64, POINTER(Out)]),
    "canergy_client_join": (None, [POINTER(CClientState), c_uint16, c_uint64, POINTER(Out)]),
    "canergy_node_start": (
        c_int,
        [
            POINTER(CNodeState),
            POINTER(NodeConfig),
            c_void_p,
            c_size_t,
            c_uint16,
            c_uint64,
            POINTER(Out),
        ],
    ),
    "canergy_node_on_frame": (
        c_int,
        [POINTER(CNodeState), POINTER(RxFrame), c_uint64, POINTER(Out)],
    ),
    "canergy_node_poll": (None, [POINTER(CNodeState), c_uint64, POINTER(Out)]),
    "canergy_node_draw": (c_uint32, [POINTER(CNodeState), c_uint32, c_uint64, POINTER(Out)]),
    "canergy_node_deadline": (c_uint64, [POINTER(CNodeState)]),
}

# -- building and loading ---------------------------------------------------------------------


def make(*targets: str) -> None:
    """``make -C firmware TARGET...``; fails the test run loudly when there is no C toolchain."""
    for tool in ("make", os.environ.get("CC", "cc")):
        if shutil.which(tool) is None:
            pytest.fail(
                f"the C tests need {tool!r}: install build-essential (apt-get install -y "
                "build-essential)",
                pytrace=False,
            )
    run = subprocess.run(
        ["make", "-C", str(FIRMWARE), "--no-print-directory", *targets],
        capture_output=True,
        text=True,
        check=False,
    )
    if run.returncode != 0:
        pytest.fail(f"make {' '.join(targets)} failed:\n{run.stdout}\n{run.stderr}", pytrace=False)


def _load(name: str) -> ctypes.CDLL:
    make(f"build/{name}")
    lib = ctypes.CDLL(str(BUILD / name))
    for fn, (restype, argtypes) in _SIGNATURES.items():
        f = getattr(lib, fn)
        f.restype, f.argtypes = restype, argtypes
    return lib


@functools.cache
def library(variant: str = "") -> ctypes.CDLL:
    """The library as the tests run it; ``variant="broken"``: with a deliberately broken rule."""
    if variant == "broken":
        return _load("libcanergy-broken.so")
    return _load("libcanergy-asan.so" if SANITIZER == "asan" else "libcanergy-test.so")


# -- Python state in C terms ------------------------------------------------------------------


def c_view(s: ClientState) -> dict[str, int]:
    """What the C client holds for this Python state (counters modulo 2**32)."""
    assert s.credited % 1000 == 0 and s.held_amount % 1000 == 0 and not s.timeout_commit
    return {
        "usable_uj": s.usable,
        "credited_mj": s.credited // 1000 & U32,
        "spent_uj": s.spent,
        "last_tx": s.last_tx & U32,
        "return_seq": s.return_seq & U32,
        "return_pending_uj": s.return_pending,
        "outcome": int(s.outcome),
        "flags": int(s.credited_unknown) | (FLAG_PENDING_DRAW if s.pending_draw else 0),
        "phase": PHASES[s.phase],
        "held_tx": s.held_tx & U32,
        "held_amount_mj": s.held_amount // 1000,
        "nonce": s.nonce,
        "deadline": NEVER if s.deadline is None else s.deadline,
        "return_deadline": NEVER if s.return_deadline is None else s.return_deadline,
    }


def struct_view(c: CClientState) -> dict[str, int]:
    r = c.rec
    return {
        "usable_uj": r.usable_uj,
        "credited_mj": r.credited_mj,
        "spent_uj": r.spent_uj,
        "last_tx": r.last_tx,
        "return_seq": r.return_seq,
        "return_pending_uj": r.return_pending_uj,
        "outcome": r.outcome,
        "flags": r.flags,
        "phase": c.phase,
        "held_tx": c.held_tx,
        "held_amount_mj": c.held_amount_mj,
        "nonce": c.nonce,
        "deadline": c.deadline,
        "return_deadline": c.return_deadline,
    }


def events_of(actions: list[Action] | tuple[Action, ...]) -> int:
    """The C library's event bits for the notes among Python's actions."""
    bits = 0
    for a in actions:
        if isinstance(a, ClientCommitted):
            bits |= EV_TIMEOUT_COMMIT if a.by_timeout else EV_COMMITTED
        elif isinstance(a, ClientAborted):
            bits |= EV_ABORTED
        elif isinstance(a, Credited):
            bits |= EV_CREDITED
        elif isinstance(a, ReturnAcknowledged):
            bits |= EV_RETURN_ACKED
        elif isinstance(a, IntentionRefused):
            bits |= EV_REFUSED
    return bits


def frames_of(codec: Codec, actions: list[Action] | tuple[Action, ...]) -> list[tuple[int, bytes]]:
    return [codec.encode(a.message) for a in actions if isinstance(a, Send)]


def rx(arbitration_id: int, data: bytes, extended: bool = True, remote: bool = False) -> Any:
    """An rx frame and the buffer it points into (keep both alive for the call)."""
    buf = ctypes.create_string_buffer(bytes(data), max(len(data), 1))
    return RxFrame(arbitration_id, ctypes.cast(buf, c_void_p), len(data), extended, remote), buf


class CClient:
    """The C client behind ``canergy.core.Client``'s interface, fed through the C decoder.

    ``state`` rebuilds a Python ``ClientState`` from the C struct (counters as C keeps them), so
    the ledger and the harness work unchanged; ``nv`` is the NV image the C client asked to
    write, slot by slot, and ``power_loss`` restarts from those bytes as a reboot would.
    """

    def __init__(
        self,
        node: int,
        *,
        timing: Timing | None = None,
        state: ClientState | None = None,
        id_base: int = DEFAULT_ID_BASE,
        lib: ctypes.CDLL | None = None,
        rules: str = "hardened",
    ) -> None:
        self.lib = lib or library()
        self.node = node
        self.timing = timing or Timing()
        self.codec = Codec(id_base)
        self.config = ClientConfig(
            id_base,
            self.timing.command_timeout_us,
            self.timing.return_retry_us,
            node,
            RULES[rules],
            self.timing.window,
        )
        self.c = CClientState()
        self.out = Out()
        self.nv = bytearray(2 * SLOT)
        self.last_status = 0
        self.lib.canergy_client_start(
            ctypes.byref(self.c), ctypes.byref(self.config), None, 0, 0, 0, ctypes.byref(self.out)
        )
        self.set_state(state or ClientState(node))

    # -- state in and out ---------------------------------------------------------------------
    def set_state(self, s: ClientState) -> None:
        v = c_view(s)
        r = self.c.rec
        for name in (
            "usable_uj",
            "credited_mj",
            "spent_uj",
            "last_tx",
            "return_seq",
            "return_pending_uj",
            "outcome",
            "flags",
        ):
            setattr(r, name, v[name])
        for name in ("phase", "held_tx", "held_amount_mj", "nonce", "deadline", "return_deadline"):
            setattr(self.c, name, v[name])

    def view(self) -> dict[str, int]:
        return struct_view(self.c)

    @property
    def state(self) -> ClientState:
        v = self.view()
        phase = {c: p for p, c in PHASES.items()}[v["phase"]]
        return ClientState(
            self.node,
            usable=v["usable_uj"],
            credited=v["credited_mj"] * 1000,
            spent=v["spent_uj"],
            last_tx=v["last_tx"],
            outcome=Outcome(v["outcome"]),
            return_seq=v["return_seq"],
            return_pending=v["return_pending_uj"],
            credited_unknown=bool(v["flags"] & FLAG_CREDITED_UNKNOWN),
            pending_draw=bool(v["flags"] & FLAG_PENDING_DRAW),
            held_tx=v["held_tx"],
            held_amount=v["held_amount_mj"] * 1000,
            phase=phase,
            nonce=v["nonce"],
            deadline=None if v["deadline"] == NEVER else v["deadline"],
            return_deadline=None if v["return_deadline"] == NEVER else v["return_deadline"],
        )

    # -- the C calls ------------------------------------------------------------------------------
    def _done(self) -> Out:
        out = self.out
        if out.persist:
            self.nv[out.nv_slot * SLOT : (out.nv_slot + 1) * SLOT] = bytes(out.nv_image)
        return out

    def frame(
        self,
        arbitration_id: int,
        data: bytes,
        now: int,
        *,
        extended: bool = True,
        remote: bool = False,
    ) -> Out:
        frame, buf = rx(arbitration_id, data, extended, remote)
        self.last_status = self.lib.canergy_client_on_frame(
            ctypes.byref(self.c), ctypes.byref(frame), now, ctypes.byref(self.out)
        )
        del buf
        return self._done()

    def message(self, msg: Message, now: int) -> Out:
        return self.frame(*self.codec.encode(msg), now)

    def timers(self, now: int) -> Out:
        self.lib.canergy_client_on_timer(ctypes.byref(self.c), now, ctypes.byref(self.out))
        return self._done()

    def command_timer(self, now: int) -> Out:
        self.lib.canergy_client_command_timer(ctypes.byref(self.c), now, ctypes.byref(self.out))
        return self._done()

    def return_timer(self, now: int) -> Out:
        self.lib.canergy_client_return_timer(ctypes.byref(self.c), now, ctypes.byref(self.out))
        return self._done()

    def do_spend(self, uj: int) -> int:
        result: int = self.lib.canergy_client_spend(
            ctypes.byref(self.c), uj, ctypes.byref(self.out)
        )
        self._done()
        return result

    def do_draw(self, uj: int, now: int) -> int:
        result: int = self.lib.canergy_client_draw(
            ctypes.byref(self.c), uj, now, ctypes.byref(self.out)
        )
        self._done()
        return result

    def resume(self, nonce: int, now: int) -> Out:
        self.lib.canergy_client_resume(ctypes.byref(self.c), nonce, now, ctypes.byref(self.out))
        return self._done()

    def do_give_back(self, uj: int, now: int) -> int:
        result: int = self.lib.canergy_client_give_back(
            ctypes.byref(self.c), uj, now, ctypes.byref(self.out)
        )
        self._done()
        return result

    def restart(self, now: int) -> Out:
        self.lib.canergy_client_restart(ctypes.byref(self.c), now, ctypes.byref(self.out))
        return self._done()

    def join(self, nonce: int, now: int) -> Out:
        self.lib.canergy_client_join(ctypes.byref(self.c), nonce, now, ctypes.byref(self.out))
        return self._done()

    def start(self, nv: bytes, nonce: int, now: int) -> int:
        """Reboot from an NV image (the bytes a port would read from offset 0)."""
        buf = ctypes.create_string_buffer(bytes(nv), max(len(nv), 1))
        result: int = self.lib.canergy_client_start(
            ctypes.byref(self.c),
            ctypes.byref(self.config),
            buf,
            len(nv),
            nonce,
            now,
            ctypes.byref(self.out),
        )
        self._done()
        return result

    # -- canergy.core.Client's interface, for the harness -----------------------------------------
    def _actions(self, out: Out) -> list[Action]:
        actions: list[Action] = [Persist()] if out.persist else []
        for arbitration_id, data in out.sent():
            actions.append(Send(self.codec.decode(arbitration_id, data)))
        return actions

    def receive(self, msg: ToClient, now: int) -> list[Action]:
        if msg.node != self.node:
            return []
        return self._actions(self.message(msg, now))

    def get_timer(self) -> int | None:
        deadline: int = self.lib.canergy_client_deadline(ctypes.byref(self.c))
        return None if deadline == NEVER else deadline

    def handle_timer(self, now: int) -> list[Action]:
        return self._actions(self.timers(now))

    def fire_command_timer(self, now: int) -> list[Action]:
        return self._actions(self.command_timer(now))

    def fire_return_timer(self, now: int) -> list[Action]:
        return self._actions(self.return_timer(now))

    def spend(self, amount: int) -> list[Action]:
        if not 0 <= amount <= U32 or self.do_spend(amount) != OK:
            raise LocalProtocolError(f"C client refused to spend {amount} µJ")
        return self._actions(self.out)

    def give_back(self, amount: int, now: int) -> list[Action]:
        if not 0 <= amount <= U32 or self.do_give_back(amount, now) != OK:
            raise LocalProtocolError(f"C client refused to give back {amount} µJ")
        return self._actions(self.out)

    def can_give_back(self) -> bool:
        return bool(self.lib.canergy_client_can_give_back(ctypes.byref(self.c)))

    def power_loss(self, now: int) -> None:
        """A reboot: the C client starts again from the NV bytes it asked to be written."""
        if self.view()["phase"] == PHASES[Phase.JOINING]:
            self.restart(now)  # no record: the rejoin cell (keeps the nonce, as Python does)
        else:
            self.start(bytes(self.nv), 0, now)
            assert self.view()["phase"] != PHASES[Phase.JOINING], "the record was not persisted"
