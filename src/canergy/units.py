"""Units at the user's edge: parse "10J", "250mJ", "50ms", "10" into integers and back.

Inside canergy every energy is an ``int`` number of microjoules (µJ) and every power µW; at the
command line's edge durations become µs. Floats never enter the core.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from decimal import Context, Decimal

UJ_PER_J = 1_000_000
US_PER_S = 1_000_000

MAX_ENERGY_UJ = 10**9 * UJ_PER_J
"""Largest energy accepted at the edge: 1 GJ, far above any budget a bench needs."""
MAX_POWER_UW = 10**9 * UJ_PER_J
"""Largest power accepted at the edge: 1 GW."""
MAX_DURATION_US = 7 * 24 * 3600 * US_PER_S
"""Largest duration accepted at the edge: one week."""

_MAX_TEXT = 64
"""Longest quantity text accepted, so parsing any input is a small, bounded amount of work."""
_EXPONENT_CLAMP = 200
"""With at most ``_MAX_TEXT`` digits, a number whose exponent is beyond ±this is above every
maximum, or nonzero and finer than a micro-unit: clamping the exponent changes no verdict."""
_EXACT = Context(prec=2 * _MAX_TEXT)
"""Enough digits for such a number times any unit's scale: the product is exact."""
_QUANTITY = re.compile(r"^\s*([0-9]*\.?[0-9]+)(?:[eE]([+-]?[0-9]+))?\s*([a-zA-Zµ]*)\s*$")


@dataclass(frozen=True, slots=True)
class _Kind:
    """One kind of quantity: its name in messages, its units and the largest value accepted."""

    name: str
    """With its article, e.g. ``an energy``."""
    scales: dict[str, int]
    """Lower-case unit to micro-units; ``""`` is the unit of a plain number."""
    bare: str
    """The unit of a plain number as written in messages, e.g. ``J``."""
    micro: str
    """The resolution's unit, e.g. ``µJ``."""
    maximum: int
    """In micro-units."""
    examples: str


def _parse(text: str, kind: _Kind) -> int:
    """``text`` in micro-units of ``kind``; ``ValueError`` with a one-line message otherwise."""
    if len(text) > _MAX_TEXT:
        raise ValueError(f"not {kind.name}: {text[:16]!r}... is over {_MAX_TEXT} characters")
    match = _QUANTITY.match(text)
    if match is None:
        if text.strip().startswith("-"):
            raise ValueError(f"not {kind.name}: {text!r} is negative")
        raise ValueError(f"not {kind.name}: {text!r} (expected e.g. {kind.examples})")
    mantissa, exponent, unit = match.groups()
    shift = max(-_EXPONENT_CLAMP, min(_EXPONENT_CLAMP, int(exponent or 0)))
    value = _EXACT.multiply(Decimal(mantissa).scaleb(shift, _EXACT), _scale(text, unit, kind))
    if value > kind.maximum:
        largest = kind.maximum // kind.scales[""]
        raise ValueError(f"{text!r} is too large (at most {largest} {kind.bare})")
    if value != value.to_integral_value():
        raise ValueError(f"{text!r} is not a whole number of {kind.micro}")
    return int(value)


def _scale(text: str, unit: str, kind: _Kind) -> int:
    if unit.startswith("M") and unit[1:].lower() in kind.scales:
        raise ValueError(f"mega-units are not supported: {text!r} (did you mean m{unit[1:]}?)")
    scale = kind.scales.get(unit.lower())
    if scale is None:
        noun = kind.name.split()[-1]
        raise ValueError(
            f"unknown {noun} unit {unit!r} in {text!r} (expected e.g. {kind.examples})"
        )
    return scale


def _duration_kind(bare: str, plain: str) -> _Kind:
    units = {
        "us": 1,
        "µs": 1,
        "ms": 1000,
        "s": US_PER_S,
        "min": 60 * US_PER_S,
        "h": 3600 * US_PER_S,
    }
    examples = f"50ms, 1.5s, 200us, 2min or {plain}"
    return _Kind("a duration", {**units, "": units[bare]}, bare, "µs", MAX_DURATION_US, examples)


_ENERGY = _Kind(
    "an energy",
    {"": UJ_PER_J, "j": UJ_PER_J, "kj": 1000 * UJ_PER_J, "mj": 1000, "uj": 1, "µj": 1},
    "J",
    "µJ",
    MAX_ENERGY_UJ,
    "10J, 250mJ, 1500uJ or 2.5",
)
_POWER = _Kind(
    "a power",
    {"": UJ_PER_J, "w": UJ_PER_J, "kw": 1000 * UJ_PER_J, "mw": 1000, "uw": 1, "µw": 1},
    "W",
    "µW",
    MAX_POWER_UW,
    "0.5W, 200mW or 2",
)
_DURATIONS = {"s": _duration_kind("s", "0.5 (seconds)"), "ms": _duration_kind("ms", "250 (ms)")}


def parse_energy(text: str) -> int:
    """Parse an energy such as ``10J``, ``250mJ``, ``1500uJ`` or ``2.5`` (joules) into µJ.

    Raises ``ValueError`` for negative, non-numeric, unknown-unit or sub-microjoule values and
    for values above ``MAX_ENERGY_UJ``.
    """
    return _parse(text, _ENERGY)


def parse_power(text: str) -> int:
    """Parse a power such as ``0.5W``, ``200mW`` or ``2`` (watts) into µW, at most 1 GW."""
    return _parse(text, _POWER)


def parse_duration(text: str, plain: str = "s") -> int:
    """Parse a duration such as ``50ms``, ``1.5s``, ``200us``, ``2min``, ``1h`` or ``0.5`` into
    µs; a plain number is in ``plain`` units (``s`` or ``ms``). At most ``MAX_DURATION_US``."""
    return _parse(text, _DURATIONS[plain])


def format_energy(uj: int) -> str:
    """Format µJ as joules with six decimals, e.g. ``1.250000 J``."""
    sign = "-" if uj < 0 else ""
    whole, frac = divmod(abs(uj), UJ_PER_J)
    return f"{sign}{whole}.{frac:06d} J"


def format_duration(us: int) -> str:
    """Format µs in the largest unit that keeps it whole, e.g. ``50ms``, ``3s``, ``250us``."""
    for unit, scale in (("s", US_PER_S), ("ms", 1000)):
        if us % scale == 0:
            return f"{us // scale}{unit}"
    return f"{us}us"
