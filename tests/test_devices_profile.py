"""The device-profile interface (``canergy.devices.profile``) as every guard uses it: one set of
metering modes with their guarantee, shown alike in a CiA 402 drive's status and a profile
device's."""

from __future__ import annotations

from fractions import Fraction

import pytest

from canergy.cia402.counter import CounterConfig
from canergy.cia402.envelope import Limits
from canergy.cia402.guard import DriveGuard, GuardConfig
from canergy.cia402.meter import MeterConfig, MeterKind
from canergy.core import Timing
from canergy.devices.guard import DeviceConfig, DeviceGuard
from canergy.devices.odrive import MotorConstants, OdriveLimits, OdriveProfile
from canergy.devices.profile import PER_STRETCH, LimitsWritten, Metering
from canergy.devices.proxy import EXHAUSTED, ProxyBooks
from canergy.live.canopen.cia402_host import GuardedDevices
from canergy.live.supervisor.policy import TopUp

FULL = Limits(265, 265, 100_500)


@pytest.mark.parametrize(
    ("kind", "guarantee"),
    [
        (MeterKind.ENVELOPE, "drawn <= granted + bound_uj"),
        (MeterKind.COUNTER, "drawn <= granted + bound_uj"),
        (MeterKind.SAMPLED_MECHANICAL, "none"),
        (MeterKind.SAMPLED_ELECTRICAL, "none"),
    ],
)
def test_a_cia402_drive_shows_its_metering_modes_guarantee(kind: MeterKind, guarantee: str) -> None:
    counter = CounterConfig(0x2011) if kind is MeterKind.COUNTER else None
    limits = None if kind.sampled else FULL
    meter = MeterConfig(kind, bus_current_index=0x2010)
    g = DriveGuard(10, GuardConfig(meter, limits, counter), 0, 1)
    status = g.status(0)
    assert status["guarantee"] == guarantee
    assert status["meter"] == kind.value  # the CiA 402 names stay
    assert kind.metering.sound is (not kind.sampled)


@pytest.mark.parametrize("sampled", [False, True])
def test_a_profile_device_shows_the_same_guarantee_for_the_same_mode(sampled: bool) -> None:
    motor = MotorConstants(Fraction(1, 20), Fraction(1, 2))
    config = DeviceConfig(limits=OdriveLimits(5.0, 2.0), sampled=sampled)
    status = DeviceGuard(3, OdriveProfile(motor), config, 0, 1).status(0)
    mode = Metering.SAMPLED if sampled else Metering.ENVELOPE
    assert status["meter"] == mode.value
    assert status["guarantee"] == (mode.guarantee if sampled else PER_STRETCH)
    assert status["guarantee"] == ("none" if sampled else "drawn <= granted + stretches * bound_uj")
    assert status["stretches"] == (None if sampled else 1)


def test_a_profile_devices_guarantee_counts_a_bound_per_stretch_a_write_opened() -> None:
    """A writer behind the guard that raises the limits again after each of the guard's
    writes opens a stretch at its limits each time (docs/guide/drives.md): the status's
    guarantee names the stretches, the guard's own stop and one per write seen, not one bound
    over the whole attack."""
    motor = MotorConstants(Fraction(1, 20), Fraction(1, 2))
    g = DeviceGuard(3, OdriveProfile(motor), DeviceConfig(limits=OdriveLimits(5.0, 2.0)), 0, 1)
    g.on_ready(10_000, 0, OdriveLimits(5.0, 2.0), OdriveLimits(5.0, 0.0))
    for i in range(3):
        g.on_watched(20_000 + i, 20_000 + i, LimitsWritten(OdriveLimits(20.0, 20.0)))
    status = g.status(30_000)
    assert status["writes_seen"] == 3 and status["stretches"] == 4
    assert status["guarantee"] == "drawn <= granted + stretches * bound_uj"


class _Held(ProxyBooks):
    """A proxy holding ``usable`` µJ whose guard stops at ``needed``."""

    def __init__(self, usable: int, needed: int) -> None:
        super().__init__(3, Timing(), 1_000_000, 0, 1)
        self.held, self.needed = usable, needed

    @property
    def usable(self) -> int:
        return self.held

    def running(self) -> bool:
        return False

    def threshold_uj(self) -> int:
        return self.needed


def test_a_proxy_the_top_up_never_lifts_above_its_stop_is_held_not_exhausted() -> None:
    """``ProxyBooks.parked``: stopped for its budget with budget in hand, under a top-up to
    ``--target`` that cannot lift it above where its guard stops (the target not above it, or a
    shortfall below ``--min-grant``): held, with the figures and what to raise."""
    parked = _Held(78_000, 120_000).parked(EXHAUSTED, 50_000, 1_000)
    assert parked == (
        "held: 0.078 J in hand, 0.120 J needed to stop within the bound; the supervisor tops up "
        "to --target 0.050 J only (raise --target above 0.120 J, or lower the limits)"
    )
    assert _Held(78_000, 120_000).parked(EXHAUSTED, 120_000, 1_000) is not None  # to it: held
    assert _Held(78_000, 120_000).parked(EXHAUSTED, 121_000, 1_000) is None  # above: released
    assert _Held(119_500, 120_000).parked(EXHAUSTED, 130_000, 20_000) is not None  # 11 mJ short
    assert _Held(78_000, 120_000).parked("feedback stopped", 50_000, 1_000) is None
    assert _Held(0, 120_000).parked(EXHAUSTED, 50_000, 1_000) is None  # exhausted, for now


def test_a_write_found_by_the_periodic_read_back_counts_as_a_stretch() -> None:
    """Review rv2: limits raised behind the guard that only the periodic read-back finds (a
    write on another interface, or one the watcher did not see) run the device at them until
    the guard's own are in force again: a stretch like a write seen (the guard charges it from
    the read's ask, ``_take_foreign``), so ``stretches`` counts it, or the claim
    ``drawn <= granted + stretches * bound_uj`` leaves one bound out."""
    motor = MotorConstants(Fraction(1, 20), Fraction(1, 2))
    config = DeviceConfig(limits=OdriveLimits(5.0, 2.0), reread_us=1_000)
    g = DeviceGuard(3, OdriveProfile(motor), config, 0, 1)
    g.on_ready(10_000, 0, OdriveLimits(5.0, 2.0), OdriveLimits(5.0, 0.0))
    g.on_wakeup(g.next_reread or 0)  # the periodic read-back asked
    assert g.rereading is not None
    g.on_read(g.rereading + 10, OdriveLimits(20.0, 20.0))  # raised behind the guard
    status = g.status(30_000)
    assert status["guarantee"] == "drawn <= granted + stretches * bound_uj"
    assert status["stretches"] == 2


class _HeldGuard(DeviceGuard[OdriveLimits]):
    """An ODrive axis's guard whose proxy holds ``held`` µJ."""

    held = 0

    @property
    def usable(self) -> int:
        return self.held


def test_a_top_up_within_the_resume_margin_leaves_the_device_held() -> None:
    """Review rv2: the guard releases its device only above its stop threshold plus
    ``resume_margin_uj`` (10 mJ). A --target 5 mJ above the threshold tops the proxy up to a
    level where the guard keeps the device stopped for ever, so ``parked`` says held (not
    'budget exhausted', which a top-up would end), and the start-up warning is given."""
    motor = MotorConstants(Fraction(1, 20), Fraction(1, 2))
    g = _HeldGuard(3, OdriveProfile(motor), DeviceConfig(limits=OdriveLimits(5.0, 2.0)), 0, 1)
    g.on_ready(10_000, 0, OdriveLimits(5.0, 2.0), OdriveLimits(5.0, 0.0))
    target = g.threshold_uj() - g.threshold_uj() % 1000 + 5_000
    g.held = target  # topped up to --target: the level the supervisor keeps it at
    assert not g._may_resume()  # the guard keeps it stopped
    g.held = 1_000  # stopped with 1 mJ in hand: the top-up brings it to target, no further
    parked = g.parked(EXHAUSTED, target, 1_000)
    assert parked is not None and parked.startswith("held: ")
    reports: list[str] = []
    devices = {3: (g, None)}
    GuardedDevices({}, None, None, 0, devices=devices, report=reports.append, top_up=TopUp(target))  # type: ignore[dict-item]
    assert any("--target" in r for r in reports)


def test_a_top_up_below_a_whole_quantum_leaves_the_device_held() -> None:
    """Review rv2: grants are whole mJ (``messages.quantize``), --target and --min-grant need not
    be. At 130 mJ under --target 130.5 mJ and --min-grant 0.5 mJ the top-up wants 0.5 mJ and
    grants nothing, so a guard releasing above 130.2 mJ stays stopped for ever: held, not
    'budget exhausted'; from 1 mJ the top-up grants 129 mJ and gets it there."""
    assert _Held(130_000, 130_200).parked(EXHAUSTED, 130_500, 500) is not None
    assert _Held(1_000, 130_200).parked(EXHAUSTED, 130_500, 500) is not None
    assert _Held(1_000, 130_200).parked(EXHAUSTED, 131_500, 500) is None  # 131 mJ: released
