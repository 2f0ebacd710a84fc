"""argparse value types with clear messages: energies, durations, probabilities, node lists,
counts, seeds, identifier bases.

Every numeric option has an upper bound, so no value given on the command line can make a command
overflow, allocate without end or never answer; ``inf``, ``nan`` and huge numbers are one-line
argparse errors naming the option (exit status 2).
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Generic, TypeVar

from canergy.codec import MAX_EXTENDED_ID, Codec
from canergy.core.common import check_amount
from canergy.core.errors import LocalProtocolError
from canergy.messages import MAX_NODE, MIN_NODE
from canergy.units import format_duration, parse_duration, parse_energy, parse_power

_T = TypeVar("_T")

SEED_MAX = 2**32 - 1
"""Seeds are 0..2**32-1: every run reproducible from a 32-bit number."""
COUNT_MAX = 10**9
"""Largest count of frames or writes an option may ask for."""
_SHOWN = 24
"""Longest piece of an argument quoted back in an error message."""


def _shown(text: str) -> str:
    """``text`` quoted for an error message, cut short when long (one line, whatever the input)."""
    return repr(text) if len(text) <= _SHOWN else f"{text[:_SHOWN]!r}..."


def argument(parse: Callable[[str], _T], text: str) -> _T:
    """``parse(text)``, its ``ValueError`` turned into argparse's one-line error (for any
    command's value type)."""
    try:
        return parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _positive(value: int, text: str) -> int:
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be more than 0")
    return value


def energy(text: str) -> int:
    """``10J``, ``250mJ``, ``1500uJ`` or plain joules, as µJ (at most 1 GJ)."""
    return argument(parse_energy, text)


def grant_amount(text: str) -> int:
    """An energy one transaction can carry (the core's ``check_amount``): whole millijoules,
    1 mJ to 65.535 J."""
    value = energy(text)
    try:
        check_amount(value)
    except LocalProtocolError:
        raise argparse.ArgumentTypeError(
            f"{text[:24]!r}: a grant is whole millijoules from 1 mJ to 65.535 J"
        ) from None
    return value


def power(text: str) -> int:
    """``0.5W``, ``200mW`` or plain watts, as µW (at most 1 GW)."""
    return argument(parse_power, text)


def duration_or_zero(text: str) -> int:
    """``50ms``, ``1.5s``, ``200us``, ``2min``, ``1h`` or plain seconds, as µs (at most a week)."""
    return argument(parse_duration, text)


def duration(text: str) -> int:
    """A duration as for ``duration_or_zero``, more than zero."""
    return _positive(duration_or_zero(text), text)


def milliseconds(text: str) -> int:
    """A duration more than zero with plain numbers in ms (``--delay-ms 250``), as µs."""
    return _positive(argument(lambda t: parse_duration(t, plain="ms"), text), text)


def duration_at_least(low_us: int) -> Callable[[str], int]:
    """A duration as for ``duration``, at least ``low_us``."""

    def parse(text: str) -> int:
        value = duration(text)
        if value < low_us:
            raise argparse.ArgumentTypeError(
                f"{_shown(text)} is less than {format_duration(low_us)}, the least allowed"
            )
        return value

    return parse


_DURATION_SYNTAX = "e.g. 50ms, 1.5s, 2min or plain seconds, at most a week"


def add_duration(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    flag: str,
    default_us: int,
    what: str,
    *,
    low_us: int | None = None,
) -> None:
    """A duration option (µs in the namespace) whose help shows its default with its unit;
    ``low_us``: the least it may be (shown in the help too)."""
    least = "" if low_us is None else f"at least {format_duration(low_us)}, "
    parser.add_argument(
        flag,
        type=duration if low_us is None else duration_at_least(low_us),
        default=default_us,
        metavar="TIME",
        help=f"{what} (default {format_duration(default_us)}; {least}{_DURATION_SYNTAX})",
    )


def probability(text: str) -> float:
    """A number within 0..1 (``nan`` and ``inf`` are not)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a probability: {_shown(text)}") from None
    if not (math.isfinite(value) and 0.0 <= value <= 1.0):
        raise argparse.ArgumentTypeError(f"probability {_shown(text)} outside 0..1")
    return value


def bounded_int(low: int, high: int) -> Callable[[str], int]:
    """An integer within ``low..high`` (decimal, or ``0x``/``0o``/``0b`` prefixed)."""

    def parse(text: str) -> int:
        if len(text) > _SHOWN:  # also keeps int() from working through thousands of digits
            raise argparse.ArgumentTypeError(f"{_shown(text)}: not an integer in {low}..{high}")
        try:
            value = int(text, 0)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {_shown(text)}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"{value} outside {low}..{high}")
        return value

    return parse


seed = bounded_int(0, SEED_MAX)
"""A random seed, 0..2**32-1."""


def max_processes() -> int:
    """Most worker processes worth asking for here: four per core, at most 256."""
    return min(256, 4 * (os.cpu_count() or 1))


def id_base(text: str) -> int:
    """A 29-bit identifier block with its low 12 bits clear, e.g. ``0x0CE00000``."""
    value = bounded_int(0, MAX_EXTENDED_ID)(text)
    try:
        Codec(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return value


def node_ids(text: str) -> tuple[int, ...]:
    """A node list like ``1-5,9``: ids and inclusive ranges within 1-127."""
    return id_list(text, MIN_NODE, MAX_NODE)


def odrive_ids(text: str) -> tuple[int, ...]:
    """ODrive CAN Simple node ids, 0-63 (an axis's default is 0)."""
    return id_list(text, 0, 0x3F)


def id_list(text: str, low: int, high: int) -> tuple[int, ...]:
    """A list like ``1-5,9``: ids and inclusive ranges within ``low``-``high``."""
    nodes: set[int] = set()
    for part in text.split(","):
        part = part.strip()
        lo_text, sep, hi_text = part.partition("-")
        try:
            lo = int(lo_text)
            hi = int(hi_text) if sep else lo
        except ValueError:
            raise argparse.ArgumentTypeError(f"bad node list {_shown(text)} (e.g. 1-5,9)") from None
        if not low <= lo <= hi <= high:
            raise argparse.ArgumentTypeError(
                f"bad node range {_shown(part)}: ids are {low}-{high}, low to high"
            )
        nodes.update(range(lo, hi + 1))
    return tuple(sorted(nodes))


PER_ID_SYNTAX = "[IDS:]VALUE[,IDS:VALUE...]"
_PER_ID_MAX = 1000
"""Longest ``[IDS:]VALUE`` list read (a bench has at most 127 ids to name)."""


@dataclass(frozen=True, slots=True)
class PerId(Generic[_T]):
    """A flag's value per device id, as ``per_id`` reads it: ``default`` for every id not
    named, ``named`` for the ids named (each once)."""

    default: _T | None
    named: tuple[tuple[int, _T], ...] = ()

    def resolve(self, ids: Iterable[int], flag: str, ids_flag: str) -> dict[int, _T]:
        """The value of each of ``ids`` (those without one left out); ``ValueError`` naming
        ``flag`` for an id named that ``ids_flag`` does not list."""
        wanted = tuple(ids)
        for i, _ in self.named:
            if i not in wanted:
                listed = ",".join(map(str, wanted)) or "none"
                raise ValueError(f"{flag}: id {i} is not one of {ids_flag}'s ({listed})")
        named = dict(self.named)
        out = {i: named.get(i, self.default) for i in wanted}
        return {i: v for i, v in out.items() if v is not None}


def per_id(
    value: Callable[[str], _T], low: int, high: int, example: str
) -> Callable[[str], PerId[_T]]:
    """The argparse type of a flag that takes one value for all ids or values per id:
    ``VALUE`` (every id), ``IDS:VALUE`` pairs (``IDS`` as ``id_list`` reads them, within
    ``low``-``high``), or both, comma-separated, e.g. ``example``. An id named twice, or two
    plain values, is refused; ``value`` reads each value."""

    def parse(text: str) -> PerId[_T]:
        if len(text) > _PER_ID_MAX:
            raise argparse.ArgumentTypeError(f"{_shown(text)}: longer than {_PER_ID_MAX}")
        default: _T | None = None
        plain = False
        named: dict[int, _T] = {}
        for part in text.split(","):
            ids_text, sep, value_text = part.strip().rpartition(":")
            got = value(value_text.strip())
            if not sep:
                if plain:
                    raise argparse.ArgumentTypeError(
                        f"{_shown(text)}: one plain value at most (the ids not named), "
                        f"e.g. {example}"
                    )
                default, plain = got, True
                continue
            for i in id_list(ids_text, low, high):
                if i in named:
                    raise argparse.ArgumentTypeError(f"{_shown(text)}: id {i} named twice")
                named[i] = got
        return PerId(default, tuple(sorted(named.items())))

    return parse
