"""What the supervisor sees on the bus against the protocol: frames it cannot decode, frames in
its own direction from someone else, frames refused by the MAC or freshness check (authenticated
mode), and evidence of intrusion, with the stop ``--on-intrusion stop`` asks for.

Counted per node (``NodeInfo``), recorded (``intrusions.Intrusions``, ``intrusions.Refusals``)
and reported; only evidence that cannot be forged without the key in use stops the supervisor.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import can

from canergy.auth.frames import Verdict, expected_freshness, frame_direction
from canergy.core.supervisor import SupervisorCore
from canergy.live.runtime import BusCounters
from canergy.live.supervisor.intrusions import Intrusions, Refusals, frame_text
from canergy.live.supervisor.nodes import NodeInfo
from canergy.live.supervisor.stopping import Stopping
from canergy.messages import Direction, Message


class BusWatch:
    """The refusals and intrusions of the nodes ``nodes`` (their records) of ``core``, recorded
    in ``intrusions`` and ``refusals``. ``counters``: the bus loops' counters (one per bus),
    which tell authenticated mode; ``listen_only``: frames in the supervisor's direction are
    another supervisor's, watched; ``stop_on_intrusion``: evidence asks ``stopping`` (the
    supervisor's ``Stopping``, shared) to stop, unless it is stopping already."""

    def __init__(
        self,
        core: SupervisorCore,
        nodes: Mapping[int, NodeInfo],
        intrusions: Intrusions,
        refusals: Refusals,
        counters: Sequence[BusCounters],
        *,
        listen_only: bool,
        stop_on_intrusion: bool,
        stopping: Stopping,
    ) -> None:
        self.core = core
        self.nodes = nodes
        self.intrusions = intrusions
        self.refusals = refusals
        self.counters = counters
        self.listen_only = listen_only
        self.stop_on_intrusion = stop_on_intrusion
        self.stopping = stopping
        self.stopped_by_intrusion = False
        """Whether evidence stopped the supervisor (``--on-intrusion stop``)."""

    @property
    def authenticated(self) -> bool:
        """Whether the bus loop checks MACs (``--auth``): it marks the counters it shares."""
        return any(c.auth is not None for c in self.counters)

    def decode_error(self, frame: can.Message, node: int | None) -> None:
        """A frame that did not decode, counted for its node. ``node``: the session key of the
        frame's node (None: its node id)."""
        node = frame.arbitration_id & 0xFF if node is None else node
        if node in self.nodes:
            self.nodes[node].decode_errors += 1

    def foreign_direction(self, frame: can.Message, now: int, node: int | None) -> None:
        """A frame only this supervisor sends, from someone else. Authenticated mode: the bus
        loop hands over only one verified under the node's key with a freshness value this
        supervisor never used (``canergy.live.runtime.OwnDirection``): authentic evidence.
        ``node`` as in ``decode_error``."""
        node = frame.arbitration_id & 0xFF if node is None else node
        if node not in self.nodes:
            return
        if self.listen_only:  # it sends nothing: they are the supervisor's it watches
            self.nodes[node].supervisor_frames += 1
            return
        if self.authenticated:
            kind = (
                "a frame only this supervisor sends, verified under the node's key and newer "
                "than any it sent: a second supervisor holds the master key"
            )
            self.authentic_intrusion(node, frame_text(frame), kind, now)
        else:
            kind = "a frame only this supervisor sends"
            self.intrusion(node, frame_text(frame), kind, now, stop=True)

    def auth_failure(self, verdict: Verdict, frame: can.Message, now: int) -> None:
        """A refused frame (no MAC, a bad one, a stale one...): counted per node and reason
        with a rate, reported (an intrusion, logged at most once a second), never acted on:
        anyone on the bus can send one."""
        node, failure = verdict.node, verdict.failure
        if node is None or node not in self.nodes or failure is None:
            return
        reason = failure.value
        if frame_direction(frame.arbitration_id) is Direction.TO_CLIENT:
            reason += " (in the supervisor's direction)"
        what = frame_text(frame)
        self.refusals.record(node, reason, what, now)
        self.intrusions.record(node, what, reason, now, quiet=True)

    def freshness(self, msg: Message) -> int | None:
        """Authenticated mode: the freshness value of a frame to or from ``msg.node``, from this
        supervisor's counters for it (None: not a node it manages). A frame older than them (a
        replay of an earlier transaction or return) is refused as stale."""
        if msg.node not in self.nodes:
            return None
        s = self.core.session(msg.node)
        return expected_freshness(msg, s.tx, s.returns_credited)

    def intrusion(self, node: int, what: str, kind: str, now: int, *, stop: bool = False) -> None:
        """Report what no honest participant sends. ``stop``: evidence that ``--on-intrusion
        stop`` acts on without a key (a frame in this supervisor's own direction: a second
        supervisor or a spoofer); failed cross-checks are reported only (a replayed TELEMETRY or
        a duplicated classic frame must not be able to stop the supervisor). In authenticated
        mode anyone can still send such frames without a MAC: only ``authentic_intrusion``
        stops then, and ``stop`` here is reported only."""
        self.intrusions.record(node, what, kind, now)
        if stop and not self.authenticated:
            self._stop(now)

    def authentic_intrusion(self, node: int, what: str, kind: str, now: int) -> None:
        """Authentic evidence of intrusion for node ``node``: what only a holder of a key could
        have sent, checked under that key. ``--on-intrusion stop`` acts on it, in authenticated
        mode as without a key. ``foreign_direction`` calls it for a frame in this supervisor's
        own direction verified under the node's key with a freshness value this supervisor never
        used: a second supervisor holding the master key.

        The hook for a node's own report: call it for a MAC-verified message whose content says
        the node saw an intrusion (say a TELEMETRY flag), and only once that content is known
        to be fresh: a TELEMETRY's freshness value is only the high half of the node's
        transaction, so a recorded one verifies again when replayed."""
        self.intrusions.record(node, what, kind, now, authentic=True)
        self._stop(now)

    def _stop(self, now: int) -> None:
        if self.stop_on_intrusion and self.stopping.ask(now):
            self.stopped_by_intrusion = True
