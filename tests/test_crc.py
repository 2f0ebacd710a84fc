"""CRC-8 SAE J1850 against published check values (AUTOSAR SWS CRC, CRC catalogue)."""

import pytest
from hypothesis import given
from hypothesis import strategies as st

from canergy.crc import crc8, crc8_update


@pytest.mark.parametrize(
    ("data", "crc"),
    [
        (b"123456789", 0x4B),
        (bytes.fromhex("00000000"), 0x59),
        (bytes.fromhex("F20183"), 0x37),
        (bytes.fromhex("0FAA0055"), 0x79),
        (bytes.fromhex("00FF5511"), 0xB8),
        (bytes.fromhex("332255AABBCCDDEEFF"), 0xCB),
        (bytes.fromhex("926B55"), 0x8C),
        (bytes.fromhex("FFFFFFFF"), 0x74),
        (bytes.fromhex("00C0DFACAA0740"), 0x6C),
    ],
)
def test_check_values(data: bytes, crc: int) -> None:
    assert crc8(data) == crc


@given(st.binary(max_size=16), st.binary(max_size=16))
def test_update_is_incremental(a: bytes, b: bytes) -> None:
    assert crc8(a + b) == crc8_update(crc8_update(0xFF, a), b) ^ 0xFF


@given(st.binary(min_size=1, max_size=9), st.data())
def test_detects_any_burst_within_one_byte(data: bytes, draw: st.DataObject) -> None:
    i = draw.draw(st.integers(0, len(data) - 1))
    flip = draw.draw(st.integers(1, 255))
    corrupted = bytearray(data)
    corrupted[i] ^= flip
    assert crc8(bytes(corrupted)) != crc8(data)


def _undetected_by_weight(nbytes: int) -> tuple[int, int, int]:
    """Undetected 1-, 2- and 3-bit error patterns in a codeword of nbytes data + 1 CRC byte."""
    from collections import Counter
    from itertools import combinations

    syndromes = []
    for bit in range(nbytes * 8):
        flipped = bytearray(nbytes)
        flipped[bit // 8] ^= 1 << (bit % 8)
        syndromes.append(crc8_update(0, bytes(flipped)))
    syndromes += [1 << k for k in range(8)]  # an error in the CRC byte itself
    singles = Counter(syndromes)
    pairs = Counter(a ^ b for a, b in combinations(syndromes, 2))
    return singles[0], pairs[0], sum(pairs[s] for s in syndromes) // 3


def test_hamming_distance_over_the_longest_frame() -> None:
    """Data ID (2 bytes) + 7 body bytes + CRC: HD 3, as docs/protocol.md states."""
    ones, twos, threes = _undetected_by_weight(2 + 7)
    assert (ones, twos) == (0, 0)
    assert threes == 362
