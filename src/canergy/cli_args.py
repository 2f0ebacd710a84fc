"""argparse value types with clear messages: energies, durations, probabilities, node lists,
counts."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import TypeVar

from canergy.messages import MAX_NODE, MIN_NODE
from canergy.units import format_duration, parse_duration, parse_energy, parse_power

_T = TypeVar("_T")


def _argument(parse: Callable[[str], _T], text: str) -> _T:
    """``parse(text)``, its ``ValueError`` turned into argparse's one-line error."""
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
    return _argument(parse_energy, text)


def power(text: str) -> int:
    """``0.5W``, ``200mW`` or plain watts, as µW (at most 1 GW)."""
    return _argument(parse_power, text)


def duration_or_zero(text: str) -> int:
    """``50ms``, ``1.5s``, ``200us``, ``2min``, ``1h`` or plain seconds, as µs (at most a week)."""
    return _argument(parse_duration, text)


def duration(text: str) -> int:
    """A duration as for ``duration_or_zero``, more than zero."""
    return _positive(duration_or_zero(text), text)


def milliseconds(text: str) -> int:
    """A duration more than zero with plain numbers in ms (``--delay-ms 250``), as µs."""
    return _positive(_argument(lambda t: parse_duration(t, plain="ms"), text), text)


_DURATION_SYNTAX = "e.g. 50ms, 1.5s, 2min or plain seconds, at most a week"


def add_duration(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup, flag: str, default_us: int, what: str
) -> None:
    """A duration option (µs in the namespace) whose help shows its default with its unit."""
    parser.add_argument(
        flag,
        type=duration,
        default=default_us,
        metavar="TIME",
        help=f"{what} (default {format_duration(default_us)}; {_DURATION_SYNTAX})",
    )


def probability(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a probability: {text!r}") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"probability {text} outside 0..1")
    return value


def bounded_int(low: int, high: int | None = None) -> Callable[[str], int]:
    def parse(text: str) -> int:
        try:
            value = int(text, 0)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if value < low or (high is not None and value > high):
            span = f"{low}..{high}" if high is not None else f">= {low}"
            raise argparse.ArgumentTypeError(f"{value} outside {span}")
        return value

    return parse


def node_ids(text: str) -> tuple[int, ...]:
    """A node list like ``1-5,9``: ids and inclusive ranges within 1-127."""
    nodes: set[int] = set()
    for part in text.split(","):
        part = part.strip()
        lo_text, sep, hi_text = part.partition("-")
        try:
            lo = int(lo_text)
            hi = int(hi_text) if sep else lo
        except ValueError:
            raise argparse.ArgumentTypeError(f"bad node list {text!r} (e.g. 1-5,9)") from None
        if not MIN_NODE <= lo <= hi <= MAX_NODE:
            raise argparse.ArgumentTypeError(
                f"bad node range {part!r}: ids are {MIN_NODE}-{MAX_NODE}, low to high"
            )
        nodes.update(range(lo, hi + 1))
    return tuple(sorted(nodes))
