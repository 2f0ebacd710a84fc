"""Energy units at the user's edge: parse "10J", "250mJ", "10" into integer microjoules and back.

Inside canergy every energy is an ``int`` number of microjoules (µJ). Floats never enter the core.
"""

from __future__ import annotations

import re
from decimal import Decimal, InvalidOperation

UJ_PER_J = 1_000_000

_SCALE_UJ = {"": UJ_PER_J, "j": UJ_PER_J, "kj": 1000 * UJ_PER_J, "mj": 1000, "uj": 1, "µj": 1}
_SCALE_UW = {"": UJ_PER_J, "w": UJ_PER_J, "kw": 1000 * UJ_PER_J, "mw": 1000, "uw": 1, "µw": 1}
_ENERGY = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*([a-zA-Zµ]*)\s*$")


def _parse_scaled(text: str, scales: dict[str, int], kind: str, examples: str) -> int:
    match = _ENERGY.match(text)
    if match is None:
        raise ValueError(f"not {kind}: {text!r} (expected e.g. {examples})")
    number, unit = match.groups()
    if unit.startswith("M"):
        raise ValueError(f"mega-units are not supported: {text!r} (did you mean m{unit[1:]}?)")
    scale = scales.get(unit.lower())
    if scale is None:
        noun = kind.split()[-1]
        raise ValueError(f"unknown {noun} unit {unit!r} in {text!r} (expected e.g. {examples})")
    try:
        value = Decimal(number) * scale
    except InvalidOperation as exc:  # pragma: no cover - the regex admits only valid decimals
        raise ValueError(f"not {kind}: {text!r}") from exc
    if value != value.to_integral_value():
        raise ValueError(f"{text!r} is not a whole number of micro-units")
    return int(value)


def parse_energy(text: str) -> int:
    """Parse an energy such as ``10J``, ``250mJ``, ``1500uJ`` or ``2.5`` (joules) into µJ.

    Raises ``ValueError`` for negative, non-numeric, unknown-unit or sub-microjoule values.
    """
    return _parse_scaled(text, _SCALE_UJ, "an energy", "10J, 250mJ, 1500uJ or 2.5")


def parse_power(text: str) -> int:
    """Parse a power such as ``0.5W``, ``200mW`` or ``2`` (watts) into µW."""
    return _parse_scaled(text, _SCALE_UW, "a power", "0.5W, 200mW or 2")


def format_energy(uj: int) -> str:
    """Format µJ as joules with six decimals, e.g. ``1.250000 J``."""
    sign = "-" if uj < 0 else ""
    whole, frac = divmod(abs(uj), UJ_PER_J)
    return f"{sign}{whole}.{frac:06d} J"
