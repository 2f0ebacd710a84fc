"""argparse value types with clear messages: energies, probabilities, node lists, counts."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from canergy.messages import MAX_NODE, MIN_NODE
from canergy.units import parse_energy, parse_power


def energy(text: str) -> int:
    """``10J``, ``250mJ``, ``1500uJ`` or plain joules, as µJ."""
    try:
        return parse_energy(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def power(text: str) -> int:
    """``0.5W``, ``200mW`` or plain watts, as µW."""
    try:
        return parse_power(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


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


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{text} must be > 0")
    return value


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
