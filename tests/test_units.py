import pytest

from canergy.units import (
    MAX_DURATION_US,
    MAX_ENERGY_UJ,
    format_duration,
    format_energy,
    parse_duration,
    parse_energy,
    parse_power,
)


@pytest.mark.parametrize(
    ("text", "uj"),
    [
        ("10J", 10_000_000),
        ("10", 10_000_000),
        ("2.5", 2_500_000),
        ("250mJ", 250_000),
        ("250 mJ", 250_000),
        ("1500uJ", 1500),
        ("1500µJ", 1500),
        ("0.001kJ", 1_000_000),
        ("1e-3J", 1000),
        ("0", 0),
    ],
)
def test_parse_energy(text: str, uj: int) -> None:
    assert parse_energy(text) == uj


@pytest.mark.parametrize("text", ["", "J", "-1J", "10 W", "1MJ", "0.5uJ", "nan", "1..2J"])
def test_parse_energy_rejects(text: str) -> None:
    with pytest.raises(ValueError):
        parse_energy(text)


@pytest.mark.parametrize(
    ("uj", "text"), [(0, "0.000000 J"), (1_250_000, "1.250000 J"), (-7, "-0.000007 J")]
)
def test_format_energy(uj: int, text: str) -> None:
    assert format_energy(uj) == text


@pytest.mark.parametrize("text", ["1e400J", "1e999999J", "1e900000J", "1000000001J", "2e9"])
def test_parse_energy_rejects_too_large_in_bounded_time(text: str) -> None:
    # 1e999999J once raised decimal.Overflow and 1e900000J took seconds to turn into an int
    with pytest.raises(ValueError, match=r"too large \(at most 1000000000 J\)"):
        parse_energy(text)


def test_parse_energy_limits() -> None:
    assert parse_energy("1e9J") == MAX_ENERGY_UJ
    assert parse_energy("0e999999") == 0
    assert parse_energy(f"{'0' * 60}1J") == 1_000_000
    with pytest.raises(ValueError, match="whole number of µJ"):
        parse_energy("1e-999999J")  # tiny but not zero
    with pytest.raises(ValueError, match="whole number of µJ"):
        parse_energy("1.0000000000000000000000000000001J")  # beyond 28 significant digits
    with pytest.raises(ValueError, match="over 64 characters"):
        parse_energy("1" * 100_000)


@pytest.mark.parametrize("text", ["inf", "nan", "-inf", "infJ", "-1J"])
def test_parse_energy_and_power_reject_non_finite_and_negative(text: str) -> None:
    with pytest.raises(ValueError, match="not an energy"):
        parse_energy(text)
    with pytest.raises(ValueError, match="not a power"):
        parse_power(text.replace("J", "W"))


def test_parse_power() -> None:
    assert parse_power("0.5W") == 500_000 and parse_power("200mW") == 200_000
    with pytest.raises(ValueError, match=r"too large \(at most 1000000000 W\)"):
        parse_power("1e400W")


@pytest.mark.parametrize(
    ("text", "us"),
    [
        ("50ms", 50_000),
        ("1.5s", 1_500_000),
        ("200us", 200),
        ("200µs", 200),
        ("2min", 120_000_000),
        ("1h", 3_600_000_000),
        ("0.05", 50_000),  # plain seconds, as the options always took
        ("3", 3_000_000),
        ("250 ms", 250_000),
        ("1e-3", 1000),
        ("0", 0),
        ("604800", MAX_DURATION_US),
    ],
)
def test_parse_duration(text: str, us: int) -> None:
    assert parse_duration(text) == us


def test_parse_duration_plain_ms() -> None:
    assert parse_duration("250", plain="ms") == 250_000
    assert parse_duration("1s", plain="ms") == 1_000_000


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("inf", "not a duration"),
        ("nan", "not a duration"),
        ("-1", "negative"),
        ("", "not a duration"),
        ("5 parsecs", "unknown duration unit 'parsecs'"),
        ("1e999999", r"too large \(at most 604800 s\)"),
        ("604801", "too large"),
        ("8d", "unknown duration unit"),
        ("0.0000005", "whole number of µs"),
        ("2Ms", "mega-units"),
    ],
)
def test_parse_duration_rejects(text: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        parse_duration(text)


@pytest.mark.parametrize(
    ("us", "text"), [(50_000, "50ms"), (3_000_000, "3s"), (250, "250us"), (0, "0s")]
)
def test_format_duration(us: int, text: str) -> None:
    assert format_duration(us) == text
    assert parse_duration(text) == us
