"""``canergy inline``'s checks before any bus is opened: each names the flag at fault."""

from __future__ import annotations

import pytest

from canergy.cli import main

BUSES = ["-i", "virtual", "-c", "motors", "--app-interface", "virtual", "--app-channel", "app"]


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--mit", "1,2", "--mit-nodes", "11", "--mit-model", "DM4310"], "--mit names 2 motors"),
        (["--mit", "1", "--mit-nodes", "11", "--mit-model", "AK80-9"], "give --mit-resistance"),
        (
            [
                *("--mit", "1", "--mit-nodes", "11", "--mit-model", "DM4310"),
                *("--mit-max-torque", "1", "--mit-max-power", "10"),
            ],
            "--mit-max-torque or --mit-max-power",
        ),
        (
            ["--mit", "1", "--mit-nodes", "11", "--mit-model", "DM4310", "--app-channel", "motors"],
            "name the same bus",
        ),
    ],
)
def test_bad_combinations_are_refused_naming_the_flag(
    extra: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["inline", *BUSES, *extra]) == 2
    assert message in capsys.readouterr().err
