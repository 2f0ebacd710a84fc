"""The supervisor's CANopen side: NMT start, a heartbeat watchdog, boot-up detection, SDO audit.

python-canopen calls heartbeat callbacks but has no consumer timeout; the watchdog here keeps the
time of each node's last heartbeat and judges it on the supervisor's monotonic clock. A node is
alive while its heartbeat is fresh and it reports OPERATIONAL; the service grants only to live
nodes. A boot-up message means the node restarted: it is started again and the service
reconciles its transaction state before granting (see ``SupervisorService.node_rebooted``).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import canopen

OPERATIONAL = 0x05
PRE_OPERATIONAL = 0x7F
BOOTUP = 0x00
RESTART_EVERY_US = 1_000_000
STATES = {0x00: "BOOTUP", 0x04: "STOPPED", 0x05: "OPERATIONAL", 0x7F: "PRE-OPERATIONAL"}


class CanopenManager:
    def __init__(
        self,
        network: canopen.Network,
        nodes: tuple[int, ...],
        eds: Path,
        heartbeat_timeout_us: int,
        clock: Callable[[], int],
    ) -> None:
        self.network = network
        self.timeout = heartbeat_timeout_us
        self.clock = clock
        self.remotes: dict[int, canopen.RemoteNode] = {}
        self.last_beat: dict[int, int] = {}
        self.last_state: dict[int, int] = {}
        self._bootups: set[int] = set()
        self._waiting: set[int] = set()
        self._started_at: dict[int, int] = {}
        self._lock = threading.Lock()
        for n in nodes:
            remote = canopen.RemoteNode(n, str(eds))
            network.add_node(remote)
            remote.nmt.add_heartbeat_callback(partial(self._beat, n))
            self.remotes[n] = remote

    def _beat(self, node: int, state: int) -> None:  # in the notifier's thread
        with self._lock:
            self.last_beat[node] = self.clock()
            self.last_state[node] = state
            if state == BOOTUP:
                self._bootups.add(node)
            if state in (BOOTUP, PRE_OPERATIONAL):
                self._waiting.add(node)

    def start_all(self) -> None:
        """NMT start to every node (broadcast)."""
        self.network.nmt.state = "OPERATIONAL"

    def alive(self, node: int, now: int) -> bool:
        with self._lock:
            beat = self.last_beat.get(node)
            return (
                beat is not None
                and now - beat <= self.timeout
                and self.last_state.get(node) == OPERATIONAL
            )

    def rebooted(self) -> list[int]:
        """Nodes that sent a boot-up message since the last call. Every node seen booting or
        PRE-OPERATIONAL is (re)started, at most once a second each: a start that crossed the
        node's own boot sequence is simply repeated."""
        now = self.clock()
        with self._lock:
            nodes, self._bootups = sorted(self._bootups), set()
            due = [
                n
                for n in self._waiting
                if now - self._started_at.get(n, -RESTART_EVERY_US) >= RESTART_EVERY_US
            ]
            self._waiting -= set(due)
        for n in due:
            self._started_at[n] = now
            self.remotes[n].nmt.state = "OPERATIONAL"
        return nodes

    def state_name(self, node: int) -> str | None:
        with self._lock:
            state = self.last_state.get(node)
        return None if state is None else STATES.get(state & 0x7F, hex(state))

    def audit(
        self, books: Callable[[], dict[int, dict[str, int]]], timeout_s: float = 2.0
    ) -> dict[str, Any]:
        """Each node's energy objects read by SDO and compared with the supervisor's books (read
        after them), in one call: ``read_energy`` then ``compare``."""
        return compare(self.read_energy(timeout_s), books())

    def read_energy(self, timeout_s: float = 2.0) -> dict[int, dict[str, int] | str]:
        """Each node's credited, spent and usable energy read by SDO (blocking: run it off the
        loop thread), or why it could not be read. Spent is read before usable (spending moves
        energy from usable to spent), so the two never count one µJ twice."""
        readings: dict[int, dict[str, int] | str] = {}
        for n, remote in self.remotes.items():
            remote.sdo.RESPONSE_TIMEOUT = timeout_s
            try:
                credited = int(remote.sdo["Credited uJ"].raw)
                spent = int(remote.sdo["Spent uJ"].raw)
                usable = int(remote.sdo["Usable budget uJ"].raw)
            except (canopen.SdoCommunicationError, canopen.SdoAbortedError) as exc:
                readings[n] = str(exc)
                continue
            readings[n] = {"credited_uj": credited, "spent_uj": spent, "usable_uj": usable}
        return readings


def compare(
    readings: dict[int, dict[str, int] | str], books: dict[int, dict[str, int]]
) -> dict[str, Any]:
    """The SDO audit's verdict: a node can hold at most what the books released to it (delivered
    or still reserved), less what it returned. ``books`` must be taken after the reads (on the
    thread that owns them): they only grow meanwhile, so a node found over them is over."""
    nodes: dict[str, Any] = {}
    ok = True
    for n, reading in readings.items():
        if isinstance(reading, str):
            nodes[str(n)] = {"error": reading}
            ok = False
            continue
        b = books[n]
        allowed = b["delivered_uj"] + b["reserved_uj"] - b["returned_uj"]
        node_ok = reading["usable_uj"] + reading["spent_uj"] <= allowed
        nodes[str(n)] = {
            "usable_uj": reading["usable_uj"],
            "spent_uj": reading["spent_uj"],
            "credited_uj": reading["credited_uj"],
            "books_allow_uj": allowed,
            "consistent": node_ok,
        }
        ok = ok and node_ok
    return {"nodes": nodes, "consistent": ok}
