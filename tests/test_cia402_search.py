"""A search for an application that fools the guard: hypothesis draws what the application
writes and when (target velocity and torque, mode, controlword), TPDO jitter and loss and host
pauses, in virtual time against the emulator's exact energy. In the sound modes the drive must
never draw more than it was granted plus the bound the guard showed (600 examples passed locally
before this landed; the ``ci`` profile runs 150, ``long`` 5,000)."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from canergy.cia402.envelope import StopKind
from canergy.cia402.meter import MeterKind
from canergy.units import UJ_PER_J
from firmware_model.drive.cosim import Scenario, run

DURATION_US = 1_500_000
PERIOD_US = 20_000

writes = st.one_of(
    st.tuples(st.just(0x60FF), st.integers(-150_000, 150_000)),
    st.tuples(st.just(0x6071), st.integers(-3_000, 3_000)),
    st.tuples(st.just(0x6060), st.sampled_from((3, 10))),
    st.tuples(st.just(0x6040), st.sampled_from((0x06, 0x07, 0x0F, 0x02, 0x00))),
    st.tuples(st.just(0x6083), st.integers(1_000, 20_000_000)),
)
app = st.lists(
    st.tuples(st.integers(0, DURATION_US), writes).map(lambda w: (w[0], *w[1])), max_size=40
)
modes = st.sampled_from(
    [(MeterKind.ENVELOPE, "drive"), (MeterKind.COUNTER, "drive"), (MeterKind.COUNTER, "meter")]
)


@given(
    mode=modes,
    stop=st.sampled_from(list(StopKind)),
    app=app,
    jitter=st.lists(st.integers(0, 15_000), min_size=1, max_size=6),
    lost=st.frozensets(st.integers(0, DURATION_US // PERIOD_US), max_size=10),
    pauses=st.lists(
        st.tuples(st.integers(0, DURATION_US), st.integers(1_000, 100_000)), max_size=2
    ),
    auto_enable=st.booleans(),
)
def test_no_application_profile_draws_past_the_grant_plus_the_bound(
    mode: tuple[MeterKind, str],
    stop: StopKind,
    app: list[tuple[int, int, int]],
    jitter: list[int],
    lost: frozenset[int],
    pauses: list[tuple[int, int]],
    auto_enable: bool,
) -> None:
    kind, where = mode
    r = run(
        Scenario(
            meter=kind,
            counter_on=where,
            stop=stop,
            pdo_period_us=PERIOD_US,
            pdo_jitter_us=tuple(jitter),
            pdo_lost=lost,
            pauses=tuple(pauses),
            app=tuple(app),
            auto_enable=auto_enable,
            budget_uj=2 * UJ_PER_J,
            duration_us=DURATION_US,
        )
    )
    assert r.bound_uj is not None
    assert r.drawn_uj <= r.granted_uj + r.bound_uj, (r.drawn_uj, r.granted_uj, r.guard)
    assert r.metered_uj == r.guard["spent_uj"] + r.debt_uj  # every charge spent or owed
