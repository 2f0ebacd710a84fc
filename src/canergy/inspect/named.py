"""What a frame of another protocol is, once named (``canergy.inspect.others``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True, slots=True)
class Named:
    """What a frame of another protocol is."""

    protocol: str
    """``canopen``, ``odrive``, ``moteus``, ``mit`` or ``dbc:<file name>``."""
    name: str
    node: int | None = None
    fields: dict[str, Any] = field(default_factory=dict)
    problem: str | None = None
    """Why the frame, though the protocol's, does not decode (None: it does)."""

    def text(self) -> str:
        head = f"{self.name} {self.node}" if self.node is not None else self.name
        parts = [f"{self.protocol.split(':')[0]}: {head}"]
        parts += [f"{k} {_show(v)}" for k, v in self.fields.items()]
        if self.problem:
            parts.append(f"!! {self.problem}")
        return "  ".join(parts)

    def as_json(self) -> dict[str, Any]:
        return {
            "protocol": self.protocol,
            "name": self.name,
            "node": self.node,
            "fields": {k: _plain(v) for k, v in self.fields.items()},
            "problem": self.problem,
        }


def _show(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def _plain(value: Any) -> Any:
    """A JSON value: cantools' named choices become their names, a float that is not finite
    (a moteus register's "unset", a float decoded from garbage) its text (JSON has no NaN)."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value if isinstance(value, int | float | str | bool) or value is None else str(value)
