"""A search over fault schedules (canergy.testing.strategies): whatever the bridge does to the
link (loss, duplication, reordering, bit flips, delays and jitter, a cut), our nodes' books
close. The plugin's fixtures live for one test, not one example: each example makes its run of
its own (canergy.testing.plugin.Books) on two virtual buses, our nodes in this process."""

from __future__ import annotations

import my_node
from hypothesis import Phase, given, settings

from canergy.testing.bus import TestBus
from canergy.testing.plugin import Books
from canergy.testing.strategies import fault_profiles, fault_schedules, partitions

SCHEDULES = fault_schedules(
    fault_profiles(max_probability=0.2, max_delay_us=2_000),
    partitions(max_start_us=1_000_000, max_length_us=500_000, max_count=1),
)


# each example is a run of a few seconds: no shrinking (it took over five minutes against a
# node that credits twice); a failing schedule is shown as it was drawn
@settings(max_examples=4, deadline=None, database=None, phases=[Phase.explicit, Phase.generate])
@given(schedule=SCHEDULES)
def test_the_books_close_whatever_the_schedule(tmp_path_factory, node_host, schedule):
    books = Books(tmp_path_factory.mktemp("run"))
    up, below = TestBus.virtual(), TestBus.virtual()
    try:
        nodes = my_node.InProcess(below, [1, 2], books.tmp, node_host)
        books.add_client(nodes.status, stop=nodes.stop)
        books.bridge(up, below, schedule)
        sup = books.supervisor(
            up,
            [*("--nodes", "1-2", "--initial", "10J", "--target", "1J", "--max-grant", "0.5J"),
             *("--response-timeout", "50ms")],
        )  # fmt: skip
        sup.wait_for(
            lambda s: all(n["committed"] >= 2 for n in s["nodes"].values()),
            "two grants to each node",
        )
    finally:
        books.stop_all()
    why = books.verdict()
    assert why is None, f"{why} (schedule: {schedule})"
