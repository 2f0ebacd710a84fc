"""firmware_model pieces without a bus: the actuator, telemetry and the return policy."""

from __future__ import annotations

from pathlib import Path

import pytest

from canergy.core.state import ClientState
from canergy.messages import Return, Telemetry
from firmware_model.actuator import Actuator, PowerProfile
from firmware_model.node import FirmwareNode, NodeConfig
from firmware_model.nvstore import NvStore


def test_energy_is_integrated_without_rounding_away_or_inventing() -> None:
    act = Actuator(PowerProfile.constant(0.333333), 0, 0)  # 333,333 µW
    wanted = sum(act.need(t) for t in range(12, 3_000_001, 12))  # 12 µs steps over 3 s
    assert wanted == 999_999  # 0.333333 W x 3 s, sub-µJ remainders carried


def test_a_csv_profile_repeats(tmp_path: Path) -> None:
    csv = tmp_path / "p.csv"
    csv.write_text("time_s,watts\n0,1\n0.5,0\n1.0,2\n")
    profile = PowerProfile.from_csv(csv)
    assert [profile.power_uw(t) for t in (0, 499_999, 500_000, 1_000_000, 1_499_999)] == [
        1_000_000,
        1_000_000,
        0,
        2_000_000,
        2_000_000,
    ]
    assert profile.power_uw(1_500_000) == 1_000_000  # period 1.5 s


@pytest.mark.parametrize("text", ["0,1\n0.5,-1\n", "0.2,1\n", "0,1\n0,2\n", "0,x\n1,y\n", ""])
def test_bad_profiles_are_refused_with_the_line(tmp_path: Path, text: str) -> None:
    csv = tmp_path / "p.csv"
    csv.write_text(text)
    with pytest.raises(ValueError, match=str(csv)):
        PowerProfile.from_csv(csv)


def _node(tmp_path: Path, usable: int, **config: object) -> FirmwareNode:
    nv = NvStore(tmp_path / "n.nv", 2, fsync=False)
    credited = -(-usable // 1000) * 1000  # whole quanta, as every credit is
    nv.save(ClientState(2, usable=usable, credited=credited, spent=credited - usable))
    return FirmwareNode(2, nv, NodeConfig(**config), now=0)  # type: ignore[arg-type]


def test_the_actuator_halts_exactly_at_zero(tmp_path: Path) -> None:
    node = _node(tmp_path, 250_000, power=PowerProfile.constant(1.0), tick_us=100_000)
    for t in range(100_000, 400_001, 100_000):
        node.on_wakeup(t)
    assert node.client.state.usable == 0
    assert node.actuator.halted and node.actuator.drawn_uj == 250_000
    assert NvStore(tmp_path / "n.nv", 2).load().usable == 0  # written before it ran


def test_telemetry_reports_the_level_and_flags(tmp_path: Path) -> None:
    node = _node(tmp_path, 1_500_000, low_water=2_000_000)
    (telemetry,) = [m for m in node.on_wakeup(0) if isinstance(m, Telemetry)]
    assert telemetry == Telemetry(2, 1500, Telemetry.LOW)


def test_energy_above_the_keep_level_is_given_back(tmp_path: Path) -> None:
    node = _node(tmp_path, 3_000_500, return_above=1_000_000, tick_us=100_000)
    returns = [m for m in node.on_wakeup(100_000) if isinstance(m, Return)]
    assert returns == [Return(2, 1, 2000)]  # whole millijoules only
    assert node.client.state.usable == 1_000_500


def test_parameters_written_over_canopen_survive_a_restart(tmp_path: Path) -> None:
    node = _node(tmp_path, 1_000_000, power=PowerProfile.constant(0.1), tick_us=100_000)
    node.set_parameter(0x2100, 250)  # response timeout, ms
    node.set_parameter(0x2102, 400)  # telemetry period, ms
    restarted = FirmwareNode(2, NvStore(tmp_path / "n.nv", 2), NodeConfig(), now=0)
    assert restarted.config.timing.response_timeout_us == 250_000
    assert restarted.client.timing.response_timeout_us == 250_000
    assert restarted.config.telemetry_period_us == 400_000
    assert restarted.config.power.power_uw(0) == 0  # never written: the command line's stays
    assert restarted.client.state.usable == 1_000_000  # the energy record is untouched
