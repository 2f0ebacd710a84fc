"""The C client library (firmware/) seen from Python: its cffi builds, adapters.

``library()`` builds the library once per source state with ``canergy.ccore.build`` (the builder
of ``canergy.ccore._supervisor``, its declarations read from the headers) and loads it: the UBSan
build in-process (any report aborts the interpreter, so it cannot pass unnoticed), or the
ASan+UBSan build when ``CANERGY_C_SANITIZER=asan`` (tests/test_c_asan.py re-runs the C-vs-Python
tests that way in a child pytest with libasan preloaded). A missing compiler fails loudly.

There is no copy of the C structs here: ``Msg()``, ``CSession(...)`` and the like make what the
headers declare through cffi, which checked their layout against the compiler's when it built
the module. ``CClient`` is the C client behind the interface of ``canergy.core.Client`` that the
harness and the state machines use, and ``c_view`` puts a Python ``ClientState`` into the C
library's terms (counters modulo 2**32, energy in the record's units).
"""

from __future__ import annotations

import functools
import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest

from canergy.ccore import build
from canergy.ccore.supervisor import CompiledSupervisor
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
U32 = 0xFFFF_FFFF
SANITIZER = os.environ.get("CANERGY_C_SANITIZER", "ubsan")

# -- building and loading ---------------------------------------------------------------------


def _need_toolchain() -> None:
    for tool in ("make", os.environ.get("CC", "cc")):
        if shutil.which(tool) is None:
            pytest.fail(
                f"the C tests need {tool!r}: install build-essential (apt-get install -y "
                "build-essential)",
                pytrace=False,
            )


def make(*targets: str) -> None:
    """``make -C firmware TARGET...``; fails the test run loudly when there is no C toolchain."""
    _need_toolchain()
    run = subprocess.run(
        ["make", "-C", str(FIRMWARE), "--no-print-directory", *targets],
        capture_output=True,
        text=True,
        check=False,
    )
    if run.returncode != 0:
        pytest.fail(f"make {' '.join(targets)} failed:\n{run.stdout}\n{run.stderr}", pytrace=False)


class CLib:
    """One build of the library: its functions and constants as attributes (``lib.canergy_*``,
    ``lib.CANERGY_*``), ``ffi``, which makes what its headers declare, and ``module``, the
    compiled module itself (what ``canergy.ccore.supervisor.CompiledSupervisor`` runs)."""

    def __init__(self, module: Any) -> None:
        self.module = module
        self.ffi = module.ffi
        for name in dir(module.lib):
            setattr(self, name, getattr(module.lib, name))

    def __getattr__(self, name: str) -> Any:  # the functions and constants set above
        raise AttributeError(name)

    def new(self, ctype: str, init: Any = None) -> Any:
        return self.ffi.new(ctype, init)


def compiled(variant: str) -> Path:
    """The variant's extension (``canergy.ccore.build.compiled``: once per source state); a
    missing toolchain or a failed build fails the test run loudly."""
    _need_toolchain()
    try:
        return build.compiled(variant)
    except Exception as exc:
        pytest.fail(f"building the C library ({variant}) failed: {exc}", pytrace=False)


@functools.cache
def library(variant: str = "") -> CLib:
    """The library as the tests run it (``canergy.ccore.build.load``): the UBSan build, the
    ASan+UBSan one under ``CANERGY_C_SANITIZER=asan``; ``variant="broken"``: with deliberately
    broken rules; ``variant="witnessed_only"``: the witnessed rules alone (the node port's)."""
    if variant in ("broken", "witnessed_only"):
        name = variant
    else:
        name = "asan" if SANITIZER == "asan" else "ubsan"
    compiled(name)
    return CLib(build.load(name))


def compiled_core(*args: Any, build: str = "", **kwargs: Any) -> CompiledSupervisor:
    """``canergy.ccore``'s ``CompiledSupervisor`` (``--core c``) on the tests' build of the
    library, ``library(build)`` (16 sessions): under UBSan, or ASan+UBSan in
    tests/test_c_asan.py's child; ``build="broken"``: with its broken rules."""
    return CompiledSupervisor(*args, module=library(build).module, **kwargs)


def ref(x: Any) -> Any:
    """What a C call takes for ``x``: a struct inside another by its address, else ``x``."""
    ffi = library().ffi
    return ffi.addressof(x) if ffi.typeof(x).kind == "struct" else x


def cbuf(
    data: bytes | bytearray | int = b"", size: int | None = None, lib: CLib | None = None
) -> Any:
    """A ``uint8_t[]`` holding ``data`` (at least one byte, as C needs somewhere to point);
    ``cbuf(n)``: n zero bytes."""
    ffi = (lib or library()).ffi
    if isinstance(data, int):
        data, size = b"", data
    buf = ffi.new("uint8_t[]", max(size if size is not None else len(data), len(data), 1))
    ffi.memmove(buf, bytes(data), len(data))
    return buf


def struct_bytes(x: Any) -> bytes:
    """The bytes of the struct ``x`` is or points to (or of the array ``x``)."""
    return bytes(library().ffi.buffer(ref(x)))


class Struct:
    """``struct canergy_<name>`` as the headers declare it: ``Msg()`` a zeroed one, ``Msg(a, b,
    field=c)`` initialised in the declared order (a pointer owning its memory)."""

    def __init__(self, name: str) -> None:
        self.ctype = f"struct canergy_{name}"

    @property
    def fields(self) -> tuple[str, ...]:
        return tuple(name for name, _ in library().ffi.typeof(self.ctype).fields)

    def __instancecheck__(self, x: Any) -> bool:
        ffi = library().ffi
        return isinstance(x, ffi.CData) and ffi.typeof(x).cname in (self.ctype, f"{self.ctype} *")

    def size(self, lib: CLib | None = None) -> int:
        return int((lib or library()).ffi.sizeof(self.ctype))

    def __call__(self, *args: Any, lib: CLib | None = None, **fields: Any) -> Any:
        init = dict(zip(self.fields, args, strict=False)) | fields
        ffi = (lib or library()).ffi
        for name, value in init.items():  # a struct given by pointer: its value
            kind = ffi.typeof(value) if isinstance(value, ffi.CData) else None
            if kind is not None and kind.kind == "pointer" and kind.item.kind == "struct":
                init[name] = value[0]
        return (lib or library()).ffi.new(f"{self.ctype} *", init)


Record = Struct("record")
CClientState = Struct("client")
Frame = Struct("frame")
Out = Struct("out")
Msg = Struct("msg")
CSession = Struct("session")
SessionStep = Struct("session_step")
SessionTiming = Struct("session_timing")
CSupervisor = Struct("supervisor")
CGateway = Struct("gateway")
SupervisorConfig = Struct("supervisor_config")
SupervisorEvent = Struct("supervisor_event")
SupervisorOut = Struct("supervisor_out")
RxFrame = Struct("rx_frame")
ClientConfig = Struct("client_config")
NvState = Struct("nv_state")
NodeConfig = Struct("node_config")
CNodeState = Struct("node")


def out_frames(out: Any) -> list[tuple[int, bytes]]:
    """The frames a ``struct canergy_out`` (or supervisor out) holds, as (identifier, data)."""
    return [(f.id, bytes(f.data[0 : f.dlc])) for f in out.frames[0 : out.frame_count]]


# -- the headers' constants, read from the binding (module attributes, on first use) -----------

PHASE_NAMES = {
    Phase.IDLE: "IDLE",
    Phase.AWAIT_COMMAND: "HOLDING",
    Phase.JOINING: "JOINING",
    Phase.RESUMING: "RESUMING",
    Phase.SYNCING: "SYNCING",
}
"""Python's client phases by their names in enum canergy_phase."""


def _derived(name: str) -> Any:
    lib = library()
    if name == "PHASES":
        return {p: getattr(lib, f"CANERGY_{c}") for p, c in PHASE_NAMES.items()}
    if name == "RULES":
        return {"hardened": lib.CANERGY_RULES_HARDENED, "witnessed": lib.CANERGY_RULES_WITNESSED}
    if name == "DIRECTIONS":
        return {
            None: lib.CANERGY_EITHER_WAY,
            "to_client": lib.CANERGY_TO_CLIENT,
            "to_supervisor": lib.CANERGY_TO_SUPERVISOR,
        }
    if name == "REASONS":  # C decode status -> Python reason, by name
        return {getattr(lib, f"CANERGY_DECODE_{r.name}"): r for r in DecodeErrorReason}
    renamed = {
        "SLOT": "NV_SLOT_SIZE",
        "SUPERVISOR_SLOT": "SUPERVISOR_SLOT_SIZE",
        "FLAG_CREDITED_UNKNOWN": "RECORD_CREDITED_UNKNOWN",
        "FLAG_PENDING_DRAW": "RECORD_PENDING_DRAW",
    }
    return getattr(lib, f"CANERGY_{renamed.get(name, name)}")


def _c(name: str) -> Any:
    return __getattr__(name)


def __getattr__(name: str) -> Any:
    """``OK``, ``ERR_*``, ``EV_*``, ``SLOT``, ``PHASES``…: the binding's values of the headers'
    names (nothing re-typed here)."""
    if name.startswith("_"):
        raise AttributeError(name)
    try:
        value = _derived(name)
    except AttributeError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    globals()[name] = value
    return value


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
        "flags": (int(s.credited_unknown) and _c("FLAG_CREDITED_UNKNOWN"))
        | (_c("FLAG_PENDING_DRAW") if s.pending_draw else 0),
        "phase": _c("PHASES")[s.phase],
        "held_tx": s.held_tx & U32,
        "held_amount_mj": s.held_amount // 1000,
        "nonce": s.nonce,
        "deadline": _c("NEVER") if s.deadline is None else s.deadline,
        "return_deadline": _c("NEVER") if s.return_deadline is None else s.return_deadline,
    }


def struct_view(c: Any) -> dict[str, int]:
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
            bits |= _c("EV_TIMEOUT_COMMIT") if a.by_timeout else _c("EV_COMMITTED")
        elif isinstance(a, ClientAborted):
            bits |= _c("EV_ABORTED")
        elif isinstance(a, Credited):
            bits |= _c("EV_CREDITED")
        elif isinstance(a, ReturnAcknowledged):
            bits |= _c("EV_RETURN_ACKED")
        elif isinstance(a, IntentionRefused):
            bits |= _c("EV_REFUSED")
    return bits


def frames_of(codec: Codec, actions: list[Action] | tuple[Action, ...]) -> list[tuple[int, bytes]]:
    return [codec.encode(a.message) for a in actions if isinstance(a, Send)]


def rx(
    arbitration_id: int,
    data: bytes,
    extended: bool = True,
    remote: bool = False,
    lib: CLib | None = None,
) -> Any:
    """An rx frame and the buffer it points into (keep both alive for the call)."""
    buf = cbuf(data, lib=lib)
    return RxFrame(arbitration_id, buf, len(data), extended, remote, lib=lib), buf


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
        lib: CLib | None = None,
        rules: str = "hardened",
    ) -> None:
        self.lib = lib or library()
        self.node = node
        self.timing = timing or Timing()
        self.codec = Codec(id_base)
        self.config = ClientConfig(
            lib=self.lib,
            id_base=id_base,
            command_timeout_us=self.timing.command_timeout_us,
            return_retry_us=self.timing.return_retry_us,
            node=node,
            rules=_c("RULES")[rules],
            window=self.timing.window,
        )
        self.c = CClientState(lib=self.lib)
        self.out = Out(lib=self.lib)
        self.nv = bytearray(2 * _c("SLOT"))
        self.last_status = 0
        self.lib.canergy_client_start(self.c, self.config, self.lib.ffi.NULL, 0, 0, 0, self.out)
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
        phase = {c: p for p, c in _c("PHASES").items()}[v["phase"]]
        return ClientState(
            self.node,
            usable=v["usable_uj"],
            credited=v["credited_mj"] * 1000,
            spent=v["spent_uj"],
            last_tx=v["last_tx"],
            outcome=Outcome(v["outcome"]),
            return_seq=v["return_seq"],
            return_pending=v["return_pending_uj"],
            credited_unknown=bool(v["flags"] & _c("FLAG_CREDITED_UNKNOWN")),
            pending_draw=bool(v["flags"] & _c("FLAG_PENDING_DRAW")),
            held_tx=v["held_tx"],
            held_amount=v["held_amount_mj"] * 1000,
            phase=phase,
            nonce=v["nonce"],
            deadline=None if v["deadline"] == _c("NEVER") else v["deadline"],
            return_deadline=None if v["return_deadline"] == _c("NEVER") else v["return_deadline"],
        )

    # -- the C calls ------------------------------------------------------------------------------
    def _done(self) -> Any:
        out = self.out
        if out.persist:
            self.nv[out.nv_slot * _c("SLOT") : (out.nv_slot + 1) * _c("SLOT")] = bytes(out.nv_image)
        return out

    def frame(
        self,
        arbitration_id: int,
        data: bytes,
        now: int,
        *,
        extended: bool = True,
        remote: bool = False,
    ) -> Any:
        frame, buf = rx(arbitration_id, data, extended, remote, lib=self.lib)
        self.last_status = self.lib.canergy_client_on_frame(self.c, frame, now, self.out)
        del buf
        return self._done()

    def message(self, msg: Message, now: int) -> Any:
        return self.frame(*self.codec.encode(msg), now)

    def timers(self, now: int) -> Any:
        self.lib.canergy_client_on_timer(self.c, now, self.out)
        return self._done()

    def command_timer(self, now: int) -> Any:
        self.lib.canergy_client_command_timer(self.c, now, self.out)
        return self._done()

    def return_timer(self, now: int) -> Any:
        self.lib.canergy_client_return_timer(self.c, now, self.out)
        return self._done()

    def do_spend(self, uj: int) -> int:
        result: int = self.lib.canergy_client_spend(self.c, uj, self.out)
        self._done()
        return result

    def do_draw(self, uj: int, now: int) -> int:
        result: int = self.lib.canergy_client_draw(self.c, uj, now, self.out)
        self._done()
        return result

    def resume(self, nonce: int, now: int) -> Any:
        self.lib.canergy_client_resume(self.c, nonce, now, self.out)
        return self._done()

    def do_give_back(self, uj: int, now: int) -> int:
        result: int = self.lib.canergy_client_give_back(self.c, uj, now, self.out)
        self._done()
        return result

    def restart(self, now: int) -> Any:
        self.lib.canergy_client_restart(self.c, now, self.out)
        return self._done()

    def join(self, nonce: int, now: int) -> Any:
        self.lib.canergy_client_join(self.c, nonce, now, self.out)
        return self._done()

    def start(self, nv: bytes, nonce: int, now: int) -> int:
        """Reboot from an NV image (the bytes a port would read from offset 0)."""
        buf = cbuf(nv, lib=self.lib)
        result: int = self.lib.canergy_client_start(
            self.c,
            self.config,
            buf,
            len(nv),
            nonce,
            now,
            self.out,
        )
        self._done()
        return result

    # -- canergy.core.Client's interface, for the harness -----------------------------------------
    def _actions(self, out: Any) -> list[Action]:
        actions: list[Action] = [Persist()] if out.persist else []
        for arbitration_id, data in out_frames(out):
            actions.append(Send(self.codec.decode(arbitration_id, data)))
        return actions

    def receive(self, msg: ToClient, now: int) -> list[Action]:
        if msg.node != self.node:
            return []
        return self._actions(self.message(msg, now))

    def get_timer(self) -> int | None:
        deadline: int = self.lib.canergy_client_deadline(self.c)
        return None if deadline == _c("NEVER") else deadline

    def handle_timer(self, now: int) -> list[Action]:
        return self._actions(self.timers(now))

    def fire_command_timer(self, now: int) -> list[Action]:
        return self._actions(self.command_timer(now))

    def fire_return_timer(self, now: int) -> list[Action]:
        return self._actions(self.return_timer(now))

    def spend(self, amount: int) -> list[Action]:
        if not 0 <= amount <= U32 or self.do_spend(amount) != _c("OK"):
            raise LocalProtocolError(f"C client refused to spend {amount} µJ")
        return self._actions(self.out)

    def give_back(self, amount: int, now: int) -> list[Action]:
        if not 0 <= amount <= U32 or self.do_give_back(amount, now) != _c("OK"):
            raise LocalProtocolError(f"C client refused to give back {amount} µJ")
        return self._actions(self.out)

    def can_give_back(self) -> bool:
        return bool(self.lib.canergy_client_can_give_back(self.c))

    def power_loss(self, now: int) -> None:
        """A reboot: the C client starts again from the NV bytes it asked to be written."""
        if self.view()["phase"] == _c("PHASES")[Phase.JOINING]:
            self.restart(now)  # no record: the rejoin cell (keeps the nonce, as Python does)
        else:
            self.start(bytes(self.nv), 0, now)
            assert self.view()["phase"] != _c("PHASES")[Phase.JOINING], (
                "the record was not persisted"
            )
