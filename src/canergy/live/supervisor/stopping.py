"""Whether the supervisor stops, and since when: one record its parts share.

The service begins nothing once it is set, the frame path's C call aborts what it would commit,
and the watch sets it on evidence (``--on-intrusion stop``): each reads or sets this record, none
calls back into the service.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(slots=True)
class Stopping:
    """Set once, at the first ``ask``: the supervisor then settles what is open and exits."""

    since: int | None = None
    """When the stop was asked (µs of the loop's clock), or None: running."""

    @property
    def asked(self) -> bool:
        """The supervisor stops."""
        return self.since is not None

    def ask(self, now: int) -> bool:
        """Stop from ``now``: True when this call stopped it, False when it was stopping."""
        if self.since is not None:
            return False
        self.since = now
        return True
