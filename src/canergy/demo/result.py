"""What a demo run produced: the ledger, per-node counters, fault counters and the verdict."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from canergy.demo.config import DemoConfig
from canergy.faults import FaultInjector
from canergy.ledger import Ledger


@dataclass(slots=True)
class NodeStats:
    committed: int = 0
    aborted: int = 0
    timeout_committed: int = 0
    credited_back: int = 0
    returns: int = 0
    resets: int = 0
    decode_errors: int = 0


@dataclass(slots=True)
class DemoResult:
    config: DemoConfig
    ledger: Ledger
    min_dissipated: int
    first_violation_us: int | None
    nodes: dict[int, NodeStats]
    client_usable: dict[int, int]
    client_spent: dict[int, int]
    outcomes: dict[str, int]
    transactions_started: int
    frames_sent: int
    decode_errors: int
    supervisor_resets: int
    virtual_us: int
    finished: bool
    injector: FaultInjector

    @property
    def passive(self) -> bool:
        return self.min_dissipated >= 0

    def as_json(self) -> dict[str, Any]:
        c = self.injector.counters
        return {
            **self.ledger.as_json(),
            "passive": self.passive,
            "min_dissipated_uj": self.min_dissipated,
            "first_violation_s": (
                None if self.first_violation_us is None else self.first_violation_us / 1e6
            ),
            "variant": self.config.variant,
            "seed": self.config.seed,
            "nodes": {
                str(n): {
                    "usable_uj": self.client_usable[n],
                    "spent_uj": self.client_spent[n],
                    "committed": s.committed,
                    "aborted": s.aborted,
                    "timeout_committed": s.timeout_committed,
                    "credited_back": s.credited_back,
                    "returns": s.returns,
                    "resets": s.resets,
                    "decode_errors": s.decode_errors,
                }
                for n, s in self.nodes.items()
            },
            "transactions_started": self.transactions_started,
            "supervisor_outcomes": self.outcomes,
            "supervisor_resets": self.supervisor_resets,
            "frames_sent": self.frames_sent,
            "frames_lost": c.lost,
            "frames_duplicated": c.duplicated,
            "frames_reordered": c.reordered,
            "frames_corrupted": c.corrupted,
            "decode_errors": self.decode_errors,
            "virtual_seconds": self.virtual_us / 1e6,
            "finished": self.finished,
        }
