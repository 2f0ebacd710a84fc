import pytest

from canergy.units import format_energy, parse_energy


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
