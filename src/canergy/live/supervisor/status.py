"""The supervisor's status: one JSON-able dict made from the parts it reads.

``StatusReport`` is given the parts at construction (the core's books, the per-node records,
the evidence, the frame path, the bus counters, the control socket) and names every field; the
service hands over only what its run alone knows (``Run``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from canergy.core.state import Phase
from canergy.core.supervisor import SupervisorCore
from canergy.live.runtime import BusCounters, total_counters
from canergy.live.supervisor.control import ControlServer
from canergy.live.supervisor.frame_path import CoreFramePath
from canergy.live.supervisor.intrusions import Intrusions, Refusals
from canergy.live.supervisor.nodes import NodeInfo


@dataclass(frozen=True, slots=True)
class Run:
    """What only the service's run knows, at the time of a status."""

    now: int
    uptime_us: int
    stopping: bool
    listen_only: bool
    fsync: bool
    injected_this_run: int
    granted_this_run: int
    stopped_by_intrusion: bool
    waiting_for_books: list[int | str]
    waiting_why: str | None
    started_without: dict[str, int]
    variant_mismatch: dict[str, str]
    """The nodes granted nothing because their TELEMETRY says other client rules: why, by name."""


class StatusReport:
    """Makes the service's status (``SupervisorService.status``)."""

    def __init__(
        self,
        core: SupervisorCore,
        nodes: Mapping[int, NodeInfo],
        witness: Any,
        joins: Any,
        intrusions: Intrusions,
        refusals: Refusals,
        path: CoreFramePath,
        *,
        node_name: Callable[[int], int | str],
        is_lost: Callable[[int, int], bool],
        bus_counters: BusCounters,
        buses: Mapping[str, BusCounters],
        control: ControlServer | None,
        extra_status: Callable[[int], dict[str, Any]] | None,
    ) -> None:
        """``witness`` and ``joins``: the service's (``witness.ReturnGate``, ``joins.JoinHold``
        or the compiled core's in C); ``node_name``, ``is_lost``: the service's; the rest as
        ``SupervisorService`` was given them."""
        self._core = core
        self._nodes = nodes
        self._witness = witness
        self._joins = joins
        self._intrusions = intrusions
        self._refusals = refusals
        self._path = path
        self._node_name = node_name
        self._is_lost = is_lost
        self._bus_counters = bus_counters
        self._buses = buses
        self._control = control
        self._extra = extra_status

    def status(self, run: Run) -> dict[str, Any]:
        """The whole status."""
        core = self._core
        st = core.state
        now = run.now
        nodes = self.nodes(now)
        reserved = sum(s.reserved for s in st.sessions)
        delivered = sum(s.delivered for s in st.sessions)
        returned = sum(s.returned for s in st.sessions)
        counters = total_counters(self._buses.values()) if self._buses else self._bus_counters
        buses = {name: c.as_json() for name, c in self._buses.items()}
        return {
            "role": "supervisor",
            "variant": core.variant.name,
            "core": core.implementation,
            **self._path.status(),
            "uptime_s": round(run.uptime_us / 1e6, 3),
            "stopping": run.stopping,
            "listen_only": run.listen_only,
            "fsync": run.fsync,
            "initial_uj": st.initial,
            "injected_uj": st.injected,
            "injected_this_run_uj": run.injected_this_run,
            "withdrawn_uj": st.withdrawn,
            "usable_uj": st.usable,
            "reserved_uj": reserved,
            "delivered_uj": delivered,
            "returns_credited_uj": returned,
            "granted_this_run_uj": run.granted_this_run,
            "conservation": {
                "supervisor_side_uj": st.usable + reserved,
                "out_net_uj": delivered - returned,
                "in_uj": st.initial + st.injected - st.withdrawn,
                "identity": "usable + reserved + (delivered - returned) = "
                "initial + injected - withdrawn",
                "holds": st.usable + reserved + delivered - returned
                == st.initial + st.injected - st.withdrawn,
            },
            **counters.as_json(),
            **({"buses": buses} if buses else {}),
            "intrusions": self._intrusions.total,
            "intrusion_report": self._intrusions.as_json(),
            "refused": self._refusals.as_json(now),
            **({"control_refused": self._control_refused()} if self._control else {}),
            "stopped_by_intrusion": run.stopped_by_intrusion,
            "waiting_for_books": run.waiting_for_books,
            "waiting_why": run.waiting_why,
            "started_without": run.started_without,
            "variant_mismatch": run.variant_mismatch,
            "nodes": nodes,
            **({"cia402": self._extra(now)} if self._extra else {}),
        }

    def nodes(self, now: int) -> dict[str, Any]:
        """Each node's status, by name."""
        witness, joins = self._witness, self._joins
        intrusions, refusals = self._intrusions, self._refusals
        nodes: dict[str, Any] = {}
        for s in self._core.state.sessions:
            info = self._nodes[s.node]
            nodes[str(self._node_name(s.node))] = {
                "state": s.phase.name,
                "open_tx": s.tx if s.phase is not Phase.IDLE else None,
                "reserved_uj": s.reserved,
                "delivered_uj": s.delivered,
                "returns_credited_uj": s.returned,
                "returns_credited": s.returns_credited,
                **witness.status(s.node),
                "level_uj": info.heard.level,
                "lost": self._is_lost(s.node, now),
                "committed": info.committed,
                "committed_uj": info.committed_uj,
                "aborted": info.aborted,
                "written_off": info.written_off,
                "admitted": info.admitted,
                "joins_resent": joins.resent(s.node),
                "resumes": info.resumes,
                "found_behind": info.found_behind,
                "synced": info.synced,
                "ahead_of_image_uj": info.ahead_of_image_uj,
                "counts_ignored": info.counts_ignored,
                "resyncs": info.resyncs,
                "rules": info.rules,
                "variant_mismatch": info.variant_mismatch,
                "resume_waiting": witness.resume_held(s.node),
                "returns": info.returns,
                "decode_errors": info.decode_errors,
                "supervisor_frames": info.supervisor_frames,
                "intrusions": intrusions.by_node.get(s.node, 0),
                "refused": refusals.of_node(s.node),
            }
        return nodes

    def _control_refused(self) -> dict[str, int]:
        """Connections to the control socket refused, by peer uid (-1: unreadable)."""
        assert self._control is not None
        return {str(uid): n for uid, n in sorted(dict(self._control.refused).items())}
