"""firmware_model pieces without a bus: the actuator, telemetry and the return policy."""

from __future__ import annotations

from pathlib import Path

import pytest

from canergy.core import Persist
from canergy.core.state import ClientState
from canergy.messages import USABLE_MAX_UJ, Ack, Admit, Intention, Join, Return, Telemetry
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


@pytest.mark.parametrize(
    ("usable", "gs_ahead_mj", "amount_mj"),
    [
        (1000, 8_000_000, 500),  # issue 13: a Gs 8,000 J ahead ended the whole process
        (USABLE_MAX_UJ - 499_000, 0, 500),  # the amount alone does not fit the u32 µJ field
        (4_000_000_000, 300_000, 1),  # the pay-back alone does not fit
    ],
)
def test_an_intention_that_would_overflow_the_record_is_refused_not_fatal(
    tmp_path: Path, usable: int, gs_ahead_mj: int, amount_mj: int
) -> None:
    node = _node(tmp_path, usable)
    before = node.client.state
    writes = node.nv.stats.writes
    rc_mj = before.credited // 1000
    out = node.on_message(Intention(2, before.last_tx + 1, amount_mj, rc_mj + gs_ahead_mj), 10)
    assert out == [] and node.client.state == before and node.nv.stats.writes == writes
    assert node.status()["overflow_refused"] == 1
    fits = Intention(2, before.last_tx + 1, 1, rc_mj)  # one that fits is still taken
    if usable + 1000 <= USABLE_MAX_UJ:
        assert node.on_message(fits, 20) == [Ack(2, before.last_tx + 1)]


def test_a_node_without_a_record_joins_and_reports_it(tmp_path: Path) -> None:
    node = FirmwareNode(2, NvStore(tmp_path / "none.nv", 2, fsync=False), NodeConfig(), now=0)
    (join,) = node.on_wakeup(0)[:1]
    assert isinstance(join, Join) and node.joining
    assert node.telemetry(0).flags & Telemetry.JOINING
    assert not (tmp_path / "none.nv").exists()  # nothing written before admission
    assert node.on_message(Admit(2, join.nonce ^ 1, 9, 0), 1) == []  # another start's answer
    assert node.joining
    node.on_message(Admit(2, join.nonce, 9, 3), 2)
    assert not node.joining and node.client.state.last_tx == 9
    assert NvStore(tmp_path / "none.nv", 2).load() == node.client.state  # written at once


def test_losing_books_while_booked_writes_no_blank_record(tmp_path: Path) -> None:
    """A blank record on disk would be trusted at the next start: joining never persists."""
    node = _node(tmp_path, 7000)
    before = NvStore(tmp_path / "n.nv", 2).load()
    actions = node.client.books_lost(0x1234, 0)
    assert not any(isinstance(a, Persist) for a in actions)
    assert NvStore(tmp_path / "n.nv", 2).load() == before
