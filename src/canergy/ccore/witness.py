"""The compiled core's witness: ``canergy.live.supervisor.witness.ReturnGate``'s interface over
firmware/src/witness.c, one ``struct canergy_witness`` per session, in C memory the frame path's
call reaches (``CompiledSupervisor.on_answer`` holds a RETURN and reads a TELEMETRY there).

What Python adds is words: the evidence and notes a TELEMETRY or a RETURN carries, read from the
record as it was before C changed it. One difference from Python's gate, by design (witness.h):
at most ``CANERGY_WITNESS_SLOTS`` return numbers are held per node; a RETURN with a further one
is dropped, never credited.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from canergy.live.supervisor.witness import WITNESS_REPORT_AT
from canergy.messages import SEQ_BITS, WITNESS_BITS, Debit, Return, Telemetry
from canergy.seqnum import unwrap

if TYPE_CHECKING:
    from canergy.ccore.supervisor import CompiledSupervisor


class CompiledReturnGate:
    """``ReturnGate`` in C (``CompiledSupervisor.return_gate``)."""

    implementation = "c"

    def __init__(self, core: CompiledSupervisor, hold_us: int, block_us: int, before: Any) -> None:
        """``before``: where the frame path's call leaves the record it changed, as it was."""
        b = core._b
        self.hold_us = hold_us
        self.block_us = block_us
        self._core = core
        self._ffi, self._lib = b.ffi, b.lib
        self.records: Any = b.ffi.new("struct canergy_witness[]", len(core.nodes))
        self.before = before
        self._release = b.ffi.new("struct canergy_witness_release *")
        self._msg = b.ffi.new("struct canergy_msg *")
        self._recs = {n: self.records + i for n, i in core._index.items()}
        """Each node's record (a pointer made once: the frame path reads them every pass)."""
        self._holding: set[int] = set()
        self._known: set[int] = set()
        """Nodes a TELEMETRY, RETURN or RESUME was seen of (Python's gate shows only them)."""
        self._findings = {
            "saw": int(b.lib.CANERGY_WITNESS_SAW),
            "went_back": int(b.lib.CANERGY_WITNESS_WENT_BACK),
            "since_start": int(b.lib.CANERGY_WITNESS_SINCE_START),
            "restarted": int(b.lib.CANERGY_WITNESS_RESTARTED),
        }
        self.held_verdict = int(b.lib.CANERGY_WITNESS_HELD)
        self.contradicted = int(b.lib.CANERGY_WITNESS_CONTRADICTED)
        self.full = int(b.lib.CANERGY_WITNESS_FULL)
        self.old_verdict = int(b.lib.CANERGY_WITNESS_OLD)

    def _rec(self, node: int) -> Any:
        return self._recs[node]

    # -- TELEMETRY -------------------------------------------------------------------------
    def telemetry(self, msg: Telemetry, credited: int, now: int) -> tuple[list[str], list[str]]:
        """As ``ReturnGate.telemetry``, for a TELEMETRY decoded in Python."""
        rec = self._rec(msg.node)
        self._ffi.memmove(self.before, rec, self._ffi.sizeof("struct canergy_witness"))
        m = self._msg
        m.node, m.flags, m.seq, m.witness = msg.node, msg.flags, msg.return_seq, msg.witness
        found = self._lib.canergy_witness_telemetry(rec, m, credited % 2**32, now)
        return self.telemetry_words(msg, lambda: credited, found)

    def telemetry_words(
        self, msg: Telemetry, credited: Callable[[], int], found: int
    ) -> tuple[list[str], list[str]]:
        """The words of C's findings on ``msg``, the record before it in ``before``;
        ``credited`` gives the number of the node's last debit credited (read only for the
        words of a return number gone back)."""
        self._known.add(msg.node)
        if not found:
            return [], []
        w, f = self.before, self._findings
        seen = (msg.witness - (w.witness if w.has_witness else 0)) % (1 << WITNESS_BITS)
        evidence: list[str] = []
        notes: list[str] = []
        if found & f["since_start"]:
            notes.append(f"the node reports {seen} frame(s) in its name since it started")
        elif found & f["restarted"]:
            notes.append("the node's witness count went back: it restarted")
        elif found & f["saw"]:
            evidence.append(f"the node saw {seen} frame(s) in its name that it did not send")
        if found & f["went_back"]:
            last = int(w.return_seq)
            seq = unwrap(msg.return_seq, max(credited(), last), SEQ_BITS)
            evidence.append(f"its TELEMETRY contradicts itself: return {seq} after {last}")
        return evidence, notes

    # -- RETURN, RESUME ----------------------------------------------------------------------
    def old(self, msg: Return, credited: int) -> bool:
        return unwrap(msg.seq, credited, SEQ_BITS) <= credited

    def hold(self, msg: Return, credited: int, now: int) -> str | None:
        """As ``ReturnGate.hold``, for a RETURN decoded in Python (C: none beyond the slots)."""
        rec = self._rec(msg.node)
        self._ffi.memmove(self.before, rec, self._ffi.sizeof("struct canergy_witness"))
        m = self._msg
        m.node, m.seq, m.amount_mj = msg.node, msg.seq, msg.amount_mj
        verdict = self._lib.canergy_witness_hold(rec, m, credited % 2**32, now)
        return self.hold_words(msg, credited, verdict)

    def hold_words(self, msg: Return, credited: int, verdict: int) -> str | None:
        """C's verdict on a RETURN held, in words (the record before it in ``before``)."""
        self._known.add(msg.node)
        if verdict == self.held_verdict:
            self._holding.add(msg.node)
        if verdict != self.contradicted:
            return None
        seq = unwrap(msg.seq, credited, SEQ_BITS)
        w = self.before
        amount = next(w.held[k].amount_mj for k in range(w.held_count) if w.held[k].seq == seq)
        return f"two RETURNs numbered {seq}: {amount} and {msg.amount_mj} mJ"

    def hold_resume(self, msg: Debit, credited: int, now: int, hold: bool) -> bool:
        self._known.add(msg.node)
        m = self._msg
        m.node, m.nonce, m.flags = msg.node, msg.nonce, msg.flags
        m.seq, m.amount_mj, m.type = msg.seq, msg.amount_mj, msg.TYPE
        held = bool(
            self._lib.canergy_witness_hold_resume(
                self._rec(msg.node), m, credited % 2**32, now, hold
            )
        )
        if held:
            self._holding.add(msg.node)
        return held

    def release(self, node: int, credited: int, now: int) -> list[Return | Debit]:
        if not self.holds(node):  # nothing held: C would release nothing
            return []
        rec = self._rec(node)
        r = self._release
        self._lib.canergy_witness_release(rec, credited % 2**32, now, self.hold_us, r)
        out: list[Return | Debit] = []
        m = self._msg
        n = 0
        while self._lib.canergy_witness_release_at(r, node, n, m):
            if m.type == Debit.TYPE:
                out.append(Debit(m.node, m.nonce, m.flags, m.seq, m.amount_mj))
            else:
                out.append(Return(m.node, m.seq, m.amount_mj))
            n += 1
        return out

    # -- the rest of ReturnGate's -----------------------------------------------------------
    def holding(self) -> list[int]:
        self._holding = {n for n in self._holding if self.holds(n)}
        return sorted(self._holding)

    def holds(self, node: int) -> bool:
        rec = self._rec(node)
        return bool(rec.held_count or rec.has_resume)

    def next_release(self) -> int | None:
        if not self._holding:
            return None
        times = [
            int(self._lib.canergy_witness_next_release(self._rec(n), self.hold_us))
            for n in self.holding()
        ]
        earliest = min(times, default=self._core._b.never)
        return None if earliest == self._core._b.never else earliest

    def blocked(self, node: int, now: int) -> bool:
        return bool(self._lib.canergy_witness_blocked(self._rec(node), now, self.block_us))

    def resume_held(self, node: int) -> bool:
        return bool(self._rec(node).has_resume)

    def readmitted(self, node: int) -> None:
        self._lib.canergy_witness_readmitted(self._rec(node))

    def status(self, node: int) -> dict[str, int]:
        if node not in self._known:
            return {}
        rec = self._rec(node)
        return {
            "returns_held": int(rec.held_count),
            "returns_refuted": int(rec.refuted),
            "returns_resynchronised": int(rec.resynced),
        }


__all__ = ["WITNESS_REPORT_AT", "CompiledReturnGate"]
