"""One emulated actuator node, and a host running many of them on one bus.

The protocol rules are the shared core's ``Client``; this file only adds what firmware adds
around them: the NV record written before anything is sent or drawn, the actuator, telemetry,
and a return policy. A loop step never waits and keeps no history.

Under the witnessed rules (``NodeConfig.variant``) the actuator runs only on draws the supervisor
has acknowledged: the node draws a chunk ahead of its need (one DEBIT, one round trip), keeps
what was released in volatile memory (lost at a power loss: dissipated) and every start with a
record is RESUMING: nothing is spent until the supervisor confirms the record or finds it behind.
"""

from __future__ import annotations

import logging
import secrets
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import can

from canergy.auth.frames import AuthFailure, Verdict, expected_freshness, frame_direction
from canergy.codec import DecodeError
from canergy.core import (
    Action,
    Client,
    ClientCommitted,
    ClientState,
    Credited,
    IntentionRefused,
    Persist,
    Send,
    Timing,
)
from canergy.core.state import Phase
from canergy.live.supervisor.intrusions import Intrusions, frame_text
from canergy.live.supervisor.witness import WITNESS_GAP_US, ClientWitness
from canergy.messages import (
    AMOUNT_MAX_MJ,
    LEVEL_MAX_MJ,
    QUANTUM_UJ,
    SEQ_BITS,
    Admit,
    Direction,
    Intention,
    Message,
    Telemetry,
    ToClient,
    quantize,
)
from firmware_model.actuator import Actuator, PowerProfile
from firmware_model.nvstore import NvStore

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class NodeConfig:
    """Per-node behaviour; energies in µJ, times in µs."""

    power: PowerProfile = field(default_factory=lambda: PowerProfile.constant(0.0))
    tick_us: int = 100_000
    telemetry_period_us: int = 1_000_000
    low_water: int = 0
    """Telemetry is also sent at once when the level falls below this."""
    return_above: int | None = None
    """Give back whatever exceeds this level (None: keep everything)."""
    timing: Timing = field(default_factory=Timing)
    variant: str = "hardened"
    """The client's rules: ``hardened`` or ``witnessed`` (draws acknowledged before use)."""
    draw_chunk: int | None = None
    """Witnessed rules: µJ drawn ahead of need (None: two ticks at the profile's peak power)."""

    def chunk(self) -> int:
        """What the node keeps drawn ahead (witnessed rules): whole mJ, one frame's most."""
        if self.draw_chunk is not None:
            wanted = self.draw_chunk
        else:
            peak = max(p for _, p in self.power.steps)
            wanted = peak * 2 * self.tick_us // 1_000_000
        whole = -(-wanted // QUANTUM_UJ) * QUANTUM_UJ
        return min(max(whole, QUANTUM_UJ), AMOUNT_MAX_MJ * QUANTUM_UJ)


PARAM_INDEXES = (0x2100, 0x2101, 0x2102)
SEQ_MASK = (1 << SEQ_BITS) - 1


class FirmwareNode:
    """State: the core client's record, the actuator, two timers. Nothing else."""

    def __init__(self, node: int, nv: NvStore, config: NodeConfig, now: int) -> None:
        self.config = config
        self.nv = nv
        record = nv.load()
        if nv.set_aside:  # sealed store: a slot whose seal did not hold, as a damaged one
            log.warning(
                "node %d: --nv %s: slot %s: the seal does not hold (a write not finished, or the "
                "record edited): set aside, the other slot taken",
                node,
                nv.path,
                " and ".join(map(str, nv.set_aside)),
            )
        self.client = Client(
            node, variant=config.variant, timing=config.timing, state=record or ClientState(node)
        )
        self._spent_seen = self.client.state.spent
        self.outbox: list[Message] = []
        self.overflow_refused = 0
        self.joins = 0
        self.witnessing = ClientWitness()
        """Frames seen in this node's name that it did not send (TELEMETRY's ``witness``)."""
        self.ready_uj = 0
        """Witnessed rules: draws acknowledged and not yet used by the actuator (volatile)."""
        self.draws = 0
        self.draw_sent_at: int | None = None
        self.released = 0
        self.draw_rtt_sum_us = 0
        self.draw_rtt_max_us = 0
        """Draws released, the sum and the largest of their round trips (DEBIT sent to its
        acknowledgement, first sending only): the price of the witnessed rules, one per chunk."""
        self.resumes = 0
        self.found_behind = 0
        self.dropped_uj = 0
        """Of a record found behind: what it held that was dropped (usable and a pending draw)."""
        self.resumed_at: int | None = None
        self.confirm_us: int | None = None
        """How long the last RESUME waited for the supervisor's answer."""
        if record is None:  # new, wiped or corrupted: no books, so no pay-back is trusted
            self.client.power_loss(now)
            self.joins += 1
            nonce = self.witnessing.join_nonce = secrets.randbits(16)
            self.outbox = self._carry_out(self.client.books_lost(nonce, now), now)
        elif self.witnessed_rules:  # the record may be an older copy: the supervisor confirms
            nonce = self.witnessing.join_nonce = secrets.randbits(16)
            self.outbox = self._carry_out(self.client.power_loss(now, nonce), now)
            self.resumes += 1
            self.resumed_at = now
            log.warning(
                "node %d: RESUMING: started with a record (debit %d); nothing spent until the "
                "supervisor confirms it",
                node,
                self.client.state.return_seq,
            )
        else:
            self.client.power_loss(now)  # every start is a restart from the NV record
        self.actuator = Actuator(config.power, now, now)
        self.next_tick = now + config.tick_us
        self.next_telemetry = now  # announce the level at boot
        self.early_telemetry = 0
        """The earliest a frame in its name brings the next TELEMETRY forward to: the last one's
        time + ``WITNESS_GAP_US`` (two nodes on one id would answer each other's at once)."""
        self.decode_errors = 0
        self.telemetry_sent = 0
        self.was_low = False
        self.written = 0
        saved = nv.load_params()  # parameters written over CANopen before a restart
        for bit, index in enumerate(PARAM_INDEXES):
            if saved is not None and saved[3] >> bit & 1:
                self.set_parameter(index, saved[bit], persist=False)
        self.gate: Callable[[], str] = lambda: "OPERATIONAL"
        """NMT state when the node is also a CANopen slave (``canopen_node``)."""
        self.refused = 0
        self.intrusions = Intrusions(f"node {node}")

    @property
    def node(self) -> int:
        return self.client.node

    def on_message(self, msg: ToClient, now: int) -> list[Message]:
        if isinstance(msg, Intention) and self.gate() != "OPERATIONAL":
            self.refused += 1  # no grants outside OPERATIONAL: left unanswered
            return []
        asked = not self.witnessing.never_asked(msg, self.client.state.return_seq)
        if self.witnessed_rules and isinstance(msg, Admit) and not self.joining:
            asked = True  # a supervisor's SYNC (asked by nobody) or the ADMIT answering ours
        out = [] if asked else self.witness(now)
        joining, resuming, before = self.joining, self.resuming, self.client.state
        syncing = before.phase is Phase.SYNCING
        out += self._carry_out(self.client.receive(msg, now), now)
        if not syncing and self.client.state.phase is Phase.SYNCING:
            log.warning(
                "node %d: the supervisor started (SYNC): books and counts sent; nothing spent "
                "until it confirms them",
                self.node,
            )
        elif syncing and self.client.state.phase is not Phase.SYNCING:
            log.info("node %d: books confirmed after the supervisor's start", self.node)
            self.next_telemetry = now
        if (joining and not self.joining) or (resuming and not self.resuming):
            self.next_telemetry = now  # admitted: tell the supervisor at once
        if resuming and not self.resuming:
            self._confirmed(before, now)
        return out + self._draw_ahead(now)

    @property
    def witnessed_rules(self) -> bool:
        return self.client.variant.name == "witnessed"

    @property
    def resuming(self) -> bool:
        """Started with a record: RESUME sent, waiting for the supervisor's ADMIT."""
        return self.client.state.phase is Phase.RESUMING

    def _confirmed(self, before: ClientState, now: int) -> None:
        """The supervisor answered the RESUME: books confirmed, or found behind (dropped)."""
        self.confirm_us = None if self.resumed_at is None else now - self.resumed_at
        c = self.client.state
        if c.credited_unknown and not before.credited_unknown:
            dropped = before.usable + (before.return_pending if before.pending_draw else 0)
            self.found_behind += 1
            self.dropped_uj += dropped
            log.warning(
                "node %d: record older than the supervisor's: admitted afresh, %d µJ of its "
                "record dropped",
                self.node,
                dropped,
            )
        else:
            log.info(
                "node %d: books confirmed by the supervisor (debit %d)", self.node, c.return_seq
            )

    def _draw_ahead(self, now: int) -> list[Message]:
        """Witnessed rules: draw (one DEBIT) what tops the acknowledged pool up to the chunk,
        when the rules allow a debit now and the budget holds a whole mJ."""
        if not self.witnessed_rules or not self.client.can_spend():
            return []
        short = self.config.chunk() - self.ready_uj
        amount = min(-(-short // QUANTUM_UJ) * QUANTUM_UJ, quantize(self.client.state.usable))
        if short <= 0 or amount <= 0:
            return []
        self.draws += 1
        self.draw_sent_at = now
        return self._carry_out(self.client.spend(amount, now), now)

    def witness(self, now: int) -> list[Message]:
        """Someone spoke in this node's name: count it and tell the supervisor at the next
        wakeup but no sooner than ``WITNESS_GAP_US`` after the last TELEMETRY, or now
        (``ClientWitness.seen``)."""
        self.next_telemetry = min(self.next_telemetry, self.early_telemetry)
        return [self.telemetry(now)] if self.witnessing.seen() else []

    @property
    def witnessed(self) -> int:
        return self.witnessing.count

    def parameters(self) -> tuple[int, int, int]:
        return (
            self.config.timing.response_timeout_us // 1000,
            self.config.power.power_uw(0) // 1000,
            self.config.telemetry_period_us // 1000,
        )

    def set_parameter(self, index: int, value: int, *, persist: bool = True) -> None:
        """A CANopen write of 0x2100 (response timeout ms), 0x2101 (power mW) or 0x2102
        (telemetry period ms); kept in the NV file unless ``persist`` is False."""
        if index == 0x2100 and value > 0:
            t = self.config.timing
            timing = replace(
                t,
                response_timeout_us=value * 1000,
                command_timeout_us=2 * value * 1000,
                return_retry_us=2 * value * 1000,
            )
            self.config = replace(self.config, timing=timing)
            self.client.timing = timing
        elif index == 0x2101:
            self.config = replace(self.config, power=PowerProfile.constant(value / 1000))
            self.actuator.profile = self.config.power
        elif index == 0x2102 and value > 0:
            self.config = replace(self.config, telemetry_period_us=value * 1000)
        else:
            return
        self.written |= 1 << PARAM_INDEXES.index(index)
        if persist:
            self.nv.save_params((*self.parameters(), self.written))

    def next_wakeup(self) -> int:
        if self.outbox:
            return 0
        wake = min(self.next_tick, self.next_telemetry)
        timer = self.client.get_timer()
        return wake if timer is None else min(wake, timer)

    def on_wakeup(self, now: int) -> list[Message]:
        out, self.outbox = self.outbox, []
        if (timer := self.client.get_timer()) is not None and timer <= now:
            out += self._carry_out(self.client.handle_timer(now), now)
        if now >= self.next_tick:
            self.next_tick = now + self.config.tick_us
            out += self._actuate(now)
            out += self._maybe_return(now)
        low = self.client.state.usable < self.config.low_water
        if now >= self.next_telemetry or (low and not self.was_low):
            out.append(self.telemetry(now))
        self.was_low = low
        return out

    def telemetry(self, now: int) -> Telemetry:
        self.next_telemetry = now + self.config.telemetry_period_us
        self.early_telemetry = now + WITNESS_GAP_US
        self.telemetry_sent += 1
        usable = self.client.state.usable
        flags = (
            (Telemetry.LOW if usable < self.config.low_water else 0)
            | (Telemetry.HALTED if self.actuator.halted else 0)
            | (Telemetry.JOINING if self.joining else 0)
            | (Telemetry.WITNESSED if self.witnessed_rules else 0)
        )
        return Telemetry(
            self.node,
            min(usable // QUANTUM_UJ, LEVEL_MAX_MJ),
            flags,
            self.client.state.return_seq & SEQ_MASK,
            self.witnessing.report(),
        )

    def _actuate(self, now: int) -> list[Message]:
        wanted = self.actuator.need(now)
        if self.gate() == "STOPPED":
            self.actuator.run(0, wanted)  # NMT STOPPED: the actuator halts
            return []
        if self.witnessed_rules:  # only what the supervisor acknowledged
            take = min(wanted, self.ready_uj)
            self.ready_uj -= take
            self.actuator.run(take, wanted)
            return self._draw_ahead(now)
        take = min(wanted, self.client.state.usable)
        out = self._carry_out(self.client.spend(take, now), now) if take else []
        self.actuator.run(take, wanted)  # only after the spend is in NV
        return out

    def _maybe_return(self, now: int) -> list[Message]:
        keep = self.config.return_above
        if keep is None or not self.client.can_give_back():
            return []
        excess = quantize(self.client.state.usable - keep)
        if excess <= 0:
            return []
        return self._carry_out(
            self.client.give_back(min(excess, AMOUNT_MAX_MJ * QUANTUM_UJ), now), now
        )

    @property
    def joining(self) -> bool:
        """No books yet: JOIN sent, waiting for the supervisor's ADMIT."""
        return self.client.state.phase is Phase.JOINING

    def _carry_out(self, actions: list[Action], now: int) -> list[Message]:
        if self.client.state.spent != self._spent_seen and self.witnessed_rules:
            self.ready_uj += self.client.state.spent - self._spent_seen  # draws released
            if self.draw_sent_at is not None:
                rtt = now - self.draw_sent_at
                self.released += 1
                self.draw_rtt_sum_us += rtt
                self.draw_rtt_max_us = max(self.draw_rtt_max_us, rtt)
                self.draw_sent_at = None
        self._spent_seen = self.client.state.spent
        out: list[Message] = []
        for action in actions:
            if isinstance(action, Persist):
                self.nv.save(self.client.state)
            elif isinstance(action, Send):
                out.append(action.message)
            elif isinstance(action, ClientCommitted | Credited):
                self.next_telemetry = now  # report the new level right away
            elif isinstance(action, IntentionRefused):
                self.overflow_refused += 1
        return out

    def status(self) -> dict[str, Any]:
        c = self.client.state
        return {
            "node": self.node,
            "usable_uj": c.usable,
            "spent_uj": c.spent,
            "credited_uj": c.credited,
            "returned_uj": c.credited - c.spent - c.usable,
            "return_pending_uj": c.return_pending,
            "return_seq": c.return_seq,
            "last_tx": c.last_tx,
            "halted": self.actuator.halted,
            "drawn_uj": self.actuator.drawn_uj,
            "nv_writes": self.nv.stats.writes,
            "nv_fallbacks": self.nv.stats.fallbacks,
            "decode_errors": self.decode_errors,
            "nmt_state": self.gate(),
            "intentions_refused": self.refused,
            "overflow_refused": self.overflow_refused,
            "joining": self.joining,
            "joins": self.joins,
            "variant": self.client.variant.name,
            "resuming": self.resuming,
            "resumes": self.resumes,
            "found_behind": self.found_behind,
            "dropped_uj": self.dropped_uj,
            "confirm_us": self.confirm_us,
            "draws": self.draws,
            "draw_pending_uj": c.return_pending if c.pending_draw else 0,
            "ready_uj": self.ready_uj,
            "draw_round_trip_us": {
                "mean": self.draw_rtt_sum_us // self.released if self.released else None,
                "max": self.draw_rtt_max_us,
            },
            "intrusions": self.intrusions.total,
            "witnessed": self.witnessed,
            "intrusion_report": self.intrusions.as_json(),
        }


class NodeHost:
    """Many nodes behind one bus connection; implements the bus loop's ``Handler``."""

    def __init__(self, nodes: Sequence[FirmwareNode]) -> None:
        self.nodes = {n.node: n for n in nodes}
        self.foreign_node_frames = 0

    def on_message(self, msg: Message, now: int) -> Sequence[Message]:
        node = self.nodes.get(msg.node)
        if node is None or not isinstance(msg, ToClient):  # the loop decodes only S->C frames
            self.foreign_node_frames += 1  # for a node hosted elsewhere
            return ()
        return node.on_message(msg, now)

    def on_decode_error(self, error: DecodeError, frame: can.Message) -> None:
        node = self.nodes.get(frame.arbitration_id & 0xFF)
        if node is not None:
            node.decode_errors += 1

    def on_auth_failure(self, verdict: Verdict, frame: can.Message, now: int) -> None:
        node = self.nodes.get(verdict.node or 0)
        if node is None or verdict.failure is None:
            return
        if frame_direction(frame.arbitration_id) is Direction.TO_SUPERVISOR:
            node.outbox += node.witness(now)  # in its name, refused or not: reported at once
        if node.joining and verdict.failure is AuthFailure.STALE:
            return  # no counters yet: the supervisor's in-flight frames cannot match them
        node.intrusions.record(node.node, frame_text(frame), verdict.failure.value, now)

    def freshness(self, msg: Message) -> int | None:
        """Authenticated mode: a frame's freshness value from the node's own counters (None:
        a node this host does not run)."""
        node = self.nodes.get(msg.node)
        if node is None:
            return None
        c = node.client.state
        return expected_freshness(msg, c.last_tx, c.return_seq)  # older: refused as stale

    def on_foreign_direction(self, frame: can.Message, now: int) -> Sequence[Message]:
        node = self.nodes.get(frame.arbitration_id & 0xFF)
        if node is not None:  # a node never receives its own frames: someone speaks for it
            node.intrusions.record(node.node, frame_text(frame), "a frame in its name", now)
            return node.witness(now)
        return ()

    def next_wakeup(self) -> int | None:
        return min((n.next_wakeup() for n in self.nodes.values()), default=None)

    def on_wakeup(self, now: int) -> Sequence[Message]:
        out: list[Message] = []
        for node in self.nodes.values():
            if node.next_wakeup() <= now:
                out += node.on_wakeup(now)
        return out
