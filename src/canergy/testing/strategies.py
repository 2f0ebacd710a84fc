"""Hypothesis strategies for fault schedules, so a property test can search the faults a bridge
puts between a supervisor and a node (needs hypothesis: ``pip install 'canergy[testing]'``)."""

from __future__ import annotations

from hypothesis import strategies as st

from canergy.argtypes import SEED_MAX
from canergy.bridge.schedule import FaultSchedule, Partition, PowerCut
from canergy.faults import FaultProfile


def fault_profiles(
    max_probability: float = 0.3, max_delay_us: int = 5_000
) -> st.SearchStrategy[FaultProfile]:
    """Loss, duplication, reordering and bit flips up to ``max_probability`` each, a delay up to
    ``max_delay_us`` with a jitter up to it."""
    p = st.floats(0.0, max_probability, allow_nan=False)

    @st.composite
    def build(draw: st.DrawFn) -> FaultProfile:
        delay = draw(st.integers(0, max_delay_us))
        return FaultProfile(
            loss=draw(p),
            duplicate=draw(p),
            reorder=draw(p),
            corrupt=draw(p),
            delay_us=delay,
            jitter_us=draw(st.integers(0, delay)),
        )

    return build()


def partitions(
    max_start_us: int = 10_000_000, max_length_us: int = 2_000_000, max_count: int = 2
) -> st.SearchStrategy[list[Partition]]:
    """Up to ``max_count`` cuts of the link, each starting within ``max_start_us`` of the
    bridge's start and lasting up to ``max_length_us``."""
    one = st.builds(
        Partition, st.integers(0, max_start_us), st.integers(1_000, max(1_000, max_length_us))
    )
    return st.lists(one, max_size=max_count)


def power_cuts(
    nodes: list[str],
    max_start_us: int = 10_000_000,
    max_length_us: int = 2_000_000,
    max_count: int = 2,
) -> st.SearchStrategy[list[PowerCut]]:
    """Up to ``max_count`` power cuts of the node processes named ``nodes`` (as
    ``canergy_spawn`` names them), each starting within ``max_start_us`` of the bridge's start
    and lasting 1 ms to ``max_length_us``."""
    one = st.builds(
        PowerCut,
        st.integers(0, max_start_us),
        st.integers(1_000, max(1_000, max_length_us)),
        st.sampled_from(nodes),
    )
    return st.lists(one, max_size=max_count)


def fault_schedules(
    profiles: st.SearchStrategy[FaultProfile] | None = None,
    cuts: st.SearchStrategy[list[Partition]] | None = None,
    power: st.SearchStrategy[list[PowerCut]] | None = None,
) -> st.SearchStrategy[FaultSchedule]:
    """A fresh ``FaultSchedule`` per example: a profile, a seed, partitions and power cuts (by
    default ``fault_profiles()``, ``partitions()`` and none: give ``power=power_cuts([...])``
    for node processes); give it to ``canergy_bridge(schedule=...)``."""
    return st.builds(
        FaultSchedule,
        profiles if profiles is not None else fault_profiles(),
        st.integers(0, SEED_MAX),
        cuts if cuts is not None else partitions(),
        power if power is not None else st.just([]),
    )
