"""Serial-number arithmetic (RFC 1982 style) for the wire's narrow wrapping counters."""

from __future__ import annotations


def wrap(value: int, bits: int) -> int:
    """The ``bits``-wide wire form of an unbounded counter."""
    return value & ((1 << bits) - 1)


def unwrap(wire: int, reference: int, bits: int) -> int:
    """The unbounded value congruent to ``wire`` that lies nearest to ``reference``.

    Exact while the true value is within ``2**(bits-1)`` of the reference; farther away the
    result is always nearer the reference than the truth, which the protocol treats as stale.
    """
    modulus = 1 << bits
    diff = (wire - reference) % modulus
    if diff >= modulus >> 1:
        diff -= modulus
    return reference + diff
