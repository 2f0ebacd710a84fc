"""A gateway process: a client on the bus above, a supervisor on the bus below, one core.

``Uplink`` is the bus loop's handler for the upstream bus: it feeds the gateway core's client
role, reports the downstream usable budget as the gateway's level (so the supervisor above tops
it up like any node), and returns what the downstream budget holds above ``return_above``.
The downstream bus is served by an ordinary ``SupervisorService`` over the core's supervisor
role. Both save through ``GatewayFiles.save``: one file, written before any frame of the step.

Upstream the gateway is a node like any other: in authenticated mode (``canergy gateway
--upstream-auth``) its frames carry MACs under its own node key and ``Uplink.freshness`` gives
their freshness values from its client counters; frames refused there are counted, never acted
on. It is also the witness for its own id, as a node is: frames in its name that it did not send
(and answers to what it never asked) are counted in its TELEMETRY's ``witness``, which also
carries its return number, so a supervisor above without a key credits its RETURNs once its own
TELEMETRY confirms them (``canergy.live.supervisor.witness``).

Under the witnessed rules upstream every start is a RESUME the supervisor above confirms; until
then nothing is granted below (``DownstreamService``): the status says so (``waiting_for_upstream``)
and so does stderr, at the start and when the record is confirmed or found behind.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from canergy.auth.frames import AuthFailure, Verdict, expected_freshness, frame_direction
from canergy.codec import DecodeError
from canergy.core import Action, Credited, Persist, Send
from canergy.core.actions import ClientCommitted, IntentionRefused
from canergy.core.gateway import Gateway, link_gap
from canergy.core.state import Phase
from canergy.core.supervisor import SupervisorCore
from canergy.live.gateway.state import save_gateway
from canergy.live.runtime import BusCounters, Outgoing
from canergy.live.supervisor.intrusions import Intrusions, Refusals, frame_text
from canergy.live.supervisor.service import ServiceConfig, ServiceParts, SupervisorService
from canergy.live.supervisor.witness import WITNESS_GAP_US, ClientWitness
from canergy.messages import (
    AMOUNT_MAX_MJ,
    LEVEL_MAX_MJ,
    QUANTUM_UJ,
    SEQ_BITS,
    Admit,
    Direction,
    Message,
    Telemetry,
    ToClient,
    quantize,
)

log = logging.getLogger(__name__)

SEQ_MASK = (1 << SEQ_BITS) - 1


@dataclass(frozen=True, slots=True)
class UplinkConfig:
    telemetry_period_us: int = 100_000
    return_above: int | None = None
    """Return the downstream usable budget above this upstream (None: never)."""
    tick_us: int = 50_000


def give_back_amount(usable: int, keep: int) -> int:
    """What goes back above: the downstream budget beyond ``keep``, in whole quanta, at most one
    frame's amount (0: none). The C gateway's twin: ``canergy_gateway_give_back_amount``."""
    excess = quantize(usable - keep)
    return min(excess, AMOUNT_MAX_MJ * QUANTUM_UJ) if excess > 0 else 0


class GatewayFiles:
    """Where the gateway's one record goes."""

    def __init__(self, gateway: Gateway, path: Path | None, *, fsync: bool = True) -> None:
        self.gateway = gateway
        self.path = path
        self.fsync = fsync
        self.writes = 0

    def save(self) -> None:
        if self.path is not None:
            save_gateway(
                self.path,
                self.gateway.state,
                self.gateway.down.variant.name,
                fsync=self.fsync,
                up_variant=self.gateway.up.variant.name,
            )
            self.writes += 1


class Uplink:
    """The upstream half of a gateway; implements ``canergy.live.runtime.Handler``."""

    def __init__(
        self,
        gateway: Gateway,
        config: UplinkConfig,
        files: GatewayFiles,
        now: int,
        *,
        counters: BusCounters | None = None,
    ) -> None:
        """``counters``: the upstream bus loop's (the status shows them)."""
        self.gateway = gateway
        self.config = config
        self.files = files
        self.next_telemetry = now
        self.early_telemetry = 0
        """The earliest a frame in its name brings the next TELEMETRY forward to: the last one's
        time + ``WITNESS_GAP_US`` (two gateways on one id would answer each other's at once)."""
        self.next_tick = now
        self.outbox: list[Message] = []
        self.decode_errors = 0
        self.refused = 0
        self.joins = 0
        self.returned = 0
        self.intrusions = Intrusions(f"gateway {gateway.up.node} (upstream)")
        self.refusals = Refusals(f"gateway {gateway.up.node} (upstream)")
        """Authenticated mode: frames for this gateway refused by the MAC or freshness check."""
        self.witnessing = ClientWitness()
        """Frames seen in this gateway's name upstream that it did not send (TELEMETRY's
        ``witness``)."""
        self.now = now
        self.counters = BusCounters() if counters is None else counters
        self._said: str | None = None
        """The wait last said on stderr (None: not waiting)."""
        self.confirmed = 0
        """Starts confirmed by the supervisor above (witnessed rules upstream)."""

    @property
    def node(self) -> int:
        return self.gateway.up.node

    def start_with_books(self, nonce: int, now: int, sync_nonce: int = 0) -> None:
        """A record (a restart, or an older copy: the gateway cannot tell); witnessed upstream:
        RESUME(``nonce``) goes above, and nothing moves until the supervisor there confirms it;
        witnessed below: SYNC(``sync_nonce``)."""
        self.outbox += self._carry_out(self.gateway.power_loss(now, nonce, sync_nonce), now)
        self._said = self.gateway.upstream_waiting()
        if self._said is not None:
            log.warning("gateway %d: %s", self.node, self._said)

    def start_without_books(self, nonce: int, now: int) -> None:
        """No record: JOIN the supervisor above (and wait to be admitted)."""
        self.joins += 1
        self.witnessing.join_nonce = nonce
        self.outbox += self._carry_out(self.gateway.books_lost(nonce, now), now)

    # -- Handler -----------------------------------------------------------------------------
    def on_message(self, msg: Message, now: int) -> Sequence[Message]:
        if msg.node != self.node or not isinstance(msg, ToClient):
            return ()
        self.now = now
        out = []
        asked = not self.witnessing.never_asked(msg, self.gateway.up.state.return_seq)
        if self.gateway.draws and isinstance(msg, Admit) and not self.joining:
            asked = True  # witnessed: a supervisor's SYNC (asked by nobody) or our RESUME's ADMIT
        if not asked:
            out += self.witness(now)
        joining, behind = self.joining, self.gateway.behind
        out += self._carry_out(self.gateway.receive_upstream(msg, now), now)
        if joining and not self.joining:
            self.next_telemetry = now
        self._say_wait(behind)
        return out

    def _say_wait(self, behind: int) -> None:
        """stderr: the upstream wait as it begins, and how it ended (confirmed or behind)."""
        why = self.gateway.upstream_waiting()
        if why == self._said:
            return
        if why is not None:
            log.warning("gateway %d: %s", self.node, why)
        elif self.gateway.behind > behind:
            self.confirmed += 1
            log.warning(
                "gateway %d: the supervisor above found this gateway's record behind (an older "
                "copy): upstream books dropped, admitted afresh, the budget below dropped (%d µJ "
                "this run); granting below again",
                self.node,
                self.gateway.dropped,
            )
        else:
            self.confirmed += 1
            log.warning(
                "gateway %d: the supervisor above confirmed this gateway's record (debit %d): "
                "granting below again",
                self.node,
                self.gateway.up.state.return_seq,
            )
        self._said = why

    def on_decode_error(self, error: DecodeError, frame: can.Message) -> None:
        if frame.arbitration_id & 0xFF == self.node:
            self.decode_errors += 1

    def on_auth_failure(self, verdict: Verdict, frame: can.Message, now: int) -> None:
        """Authenticated mode: a frame for this gateway without a MAC, with a bad one or a stale
        one. Counted by reason (``refused``) and among the intrusions, never acted on; one in its
        own direction (in its name) is witnessed and reported as a node does (``witness``)."""
        if verdict.node != self.node or verdict.failure is None:
            return
        if frame_direction(frame.arbitration_id) is Direction.TO_SUPERVISOR:
            self.outbox += self.witness(now)
        if self.joining and verdict.failure is AuthFailure.STALE:
            return  # no counters yet: the supervisor's in-flight frames cannot match them
        what, reason = frame_text(frame), verdict.failure.value
        self.refusals.record(self.node, reason, what, now)
        self.intrusions.record(self.node, what, reason, now, quiet=True)

    def freshness(self, msg: Message) -> int | None:
        """Authenticated mode: a frame's freshness value from the upstream client's counters
        (None: not this gateway's); an older one is refused as stale."""
        if msg.node != self.node:
            return None
        c = self.gateway.up.state
        return expected_freshness(msg, c.last_tx, c.return_seq)

    def on_foreign_direction(self, frame: can.Message, now: int) -> Sequence[Message]:
        if frame.arbitration_id & 0xFF == self.node:
            self.intrusions.record(
                self.node, frame_text(frame), "a frame only this node sends", now
            )
            return self.witness(now)
        return ()

    def witness(self, now: int) -> list[Message]:
        """Someone spoke in this gateway's name upstream: count it and report it at the next
        wakeup but no sooner than ``WITNESS_GAP_US`` after the last TELEMETRY, or now
        (``ClientWitness.seen``), as a node does."""
        self.next_telemetry = min(self.next_telemetry, self.early_telemetry)
        return [self.telemetry(now)] if self.witnessing.seen() else []

    @property
    def join_nonce(self) -> int | None:
        return self.witnessing.join_nonce

    def next_wakeup(self) -> int | None:
        if self.outbox:
            return 0
        times = [self.next_tick, self.next_telemetry]
        if (timer := self.gateway.up.get_timer()) is not None:
            times.append(timer)
        return min(times)

    def on_wakeup(self, now: int) -> Sequence[Message]:
        self.now = now
        out, self.outbox = self.outbox, []
        timer = self.gateway.up.get_timer()
        if timer is not None and timer <= now:
            out += self._carry_out(self.gateway.handle_upstream_timer(now), now)
        if now >= self.next_tick:
            self.next_tick = now + self.config.tick_us
            out += self._maybe_return(now)
        if now >= self.next_telemetry:
            out.append(self.telemetry(now))
        self.refusals.tick(now)
        return out

    # -- internals ---------------------------------------------------------------------------
    @property
    def joining(self) -> bool:
        return self.gateway.up.state.phase is Phase.JOINING

    def level(self) -> int:
        """What the gateway reports upstream: the budget it can still grant below."""
        return self.gateway.down.usable

    def telemetry(self, now: int) -> Telemetry:
        self.next_telemetry = now + self.config.telemetry_period_us
        self.early_telemetry = now + WITNESS_GAP_US
        level = self.level()
        flags = (Telemetry.JOINING if self.joining else 0) | (
            Telemetry.WITNESSED if self.gateway.up.variant.name == "witnessed" else 0
        )  # a node above: the rules it runs there
        return Telemetry(
            self.node,
            min(level // QUANTUM_UJ, LEVEL_MAX_MJ),
            flags,
            self.gateway.up.state.return_seq & SEQ_MASK,
            self.witnessing.report(),
        )

    def _maybe_return(self, now: int) -> list[Message]:
        keep = self.config.return_above
        if keep is None or not self.gateway.can_give_back():
            return []
        amount = give_back_amount(self.gateway.down.usable, keep)
        if not amount:
            return []
        self.returned += amount
        return self._carry_out(self.gateway.give_back(amount, now), now)

    def _carry_out(self, actions: list[Action], now: int) -> list[Message]:
        out: list[Message] = []
        for action in actions:
            if isinstance(action, Persist):
                self.files.save()  # before any frame of this step leaves
            elif isinstance(action, Send):
                out.append(action.message)
            elif isinstance(action, ClientCommitted | Credited):
                self.next_telemetry = now
            elif isinstance(action, IntentionRefused):
                self.refused += 1
        return out

    def status(self) -> dict[str, Any]:
        c = self.gateway.up.state
        return {
            "node": self.node,
            "usable_uj": c.usable,
            "spent_uj": c.spent,
            "credited_uj": c.credited,
            "return_pending_uj": c.return_pending,
            "return_seq": c.return_seq,
            "last_tx": c.last_tx,
            "joining": self.joining,
            "joins": self.joins,
            "rules": self.gateway.up.variant.name,
            "resuming": self.gateway.upstream_waiting() is not None,
            "pending_draw": c.pending_draw,
            "confirmed": self.confirmed,
            "found_behind": self.gateway.behind,
            "dropped_below_uj": self.gateway.dropped,
            "returned_this_run_uj": self.returned,
            "intentions_refused": self.refused,
            "decode_errors": self.decode_errors,
            "intrusions": self.intrusions.total,
            "witnessed": self.witnessing.count,
            "intrusion_report": self.intrusions.as_json(),
            "refused": self.refusals.as_json(self.now),
            **self.counters.as_json(),
        }


class DownstreamService(SupervisorService):
    """The gateway's supervisor role; its status also shows the upstream role (``upstream``,
    the keys a node's status has) and the link between the two (``link_gap_uj``, always 0)."""

    def __init__(
        self,
        core: SupervisorCore,
        config: ServiceConfig,
        now: int,
        parts: ServiceParts,
        *,
        uplink: Uplink | None = None,
        **given: Any,
    ) -> None:
        """``uplink``: the gateway's upstream role, whose confirmation of this gateway's start
        grants below wait for; the rest as ``SupervisorService`` takes it."""
        self.uplink = uplink
        super().__init__(core, config, now, parts, **given)

    def _start_grants(self, now: int, nodes: set[int] | None) -> list[Outgoing]:
        """No grant below while the supervisor above has not confirmed this gateway's start
        (its core refuses one too): requests wait, the status and stderr say why."""
        if self.uplink is not None and self.uplink.gateway.upstream_waiting() is not None:
            self.ready.clear()
            return []
        return super()._start_grants(now, nodes)

    def status(self) -> dict[str, Any]:
        status = super().status()
        if self.uplink is None:
            return status
        gateway = self.uplink.gateway
        return {
            **status,
            "role": "gateway",
            "upstream": self.uplink.status(),
            "waiting_for_upstream": gateway.upstream_waiting(),
            "link_gap_uj": link_gap(gateway.up.state, gateway.down.state),
            "state_writes": self.uplink.files.writes,
        }
