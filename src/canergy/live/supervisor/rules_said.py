"""Which client rules each node's TELEMETRY says it runs, against this supervisor's own.

A node whose rules differ (``Telemetry.WITNESSED`` set exactly when the supervisor's are not the
witnessed ones) is granted nothing: one side would spend or wait on what the other lacks. The
flag moves no energy: a forged one can only withhold grants from the node. Kept in each node's
record (``NodeInfo.rules``, ``NodeInfo.variant_mismatch``), which the status shows.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping

from canergy.live.supervisor.nodes import NodeInfo
from canergy.messages import Telemetry

log = logging.getLogger("canergy.live.supervisor.service")
"""Its lines read as the service's, as before this part had a module of its own."""


class RulesSaid:
    """The rules said by ``nodes`` (their records) against ``rules`` (this supervisor's
    ``--variant``); ``local_nodes`` run in this process (their TELEMETRY says nothing to check);
    ``node_name`` names a node in what is said."""

    def __init__(
        self,
        rules: str,
        nodes: Mapping[int, NodeInfo],
        local_nodes: frozenset[int],
        node_name: Callable[[int], int | str],
    ) -> None:
        self.rules = rules
        """This supervisor's rules; its nodes' TELEMETRY must say the witnessed ones exactly
        when these are."""
        self.witnessed = rules == "witnessed"
        self.nodes = nodes
        self.local_nodes = local_nodes
        self.node_name = node_name

    def other(self, said: str | None) -> bool:
        """Whether rules a node's TELEMETRY said (None: none yet) differ from this
        supervisor's: the flag tells witnessed from the rest."""
        return said is not None and (said == "witnessed") != self.witnessed

    def telemetry(self, msg: Telemetry) -> None:
        """The rules ``msg`` says its node runs (``Telemetry.WITNESSED``; without it: the
        hardened ones, as a node older than the flag). Other than this supervisor's: counted,
        and said once on stderr per change; back to the same: said too."""
        if msg.node in self.local_nodes:
            return
        info = self.nodes[msg.node]
        said = "witnessed" if msg.flags & Telemetry.WITNESSED else "hardened"
        other = self.other(said)
        if other:
            info.variant_mismatch += 1
        if said == info.rules:
            return
        info.rules = said
        if other:
            log.warning("%s", self.why(msg.node))
        elif info.variant_mismatch:
            log.warning(
                "node %s now runs the %s rules, as this supervisor: granting",
                self.node_name(msg.node),
                said,
            )

    def mismatched(self, node: int) -> bool:
        """Whether the node's last TELEMETRY said other client rules than this supervisor's."""
        return self.other(self.nodes[node].rules)

    def why(self, node: int) -> str:
        """Why a node whose rules differ (``mismatched``) is granted nothing, one line."""
        said = self.nodes[node].rules
        return (
            f"node {self.node_name(node)} runs the {said} rules, this supervisor the "
            f"{self.rules}: nothing granted to it (run both with the same --variant; a node "
            "without the rules flag in its TELEMETRY counts as hardened)"
        )

    def by_name(self) -> dict[str, str]:
        """Every node whose rules differ: why, by its name (the status's ``variant_mismatch``)."""
        return {str(self.node_name(n)): self.why(n) for n in self.nodes if self.mismatched(n)}
