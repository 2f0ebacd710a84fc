"""Grants to our nodes through a bridge that loses, duplicates or reorders frames, or cuts the
link for a while: they commit, and when the test ends canergy's plugin stops the supervisor
(which settles what is open), then the nodes, and closes the books; it fails the test naming the
node that created energy."""

from __future__ import annotations

import pytest

FATES = {"loss": "lost", "duplicate": "duplicated", "reorder": "reordered"}
"""Each fault and the bridge's count of the frames it met."""


def start(canergy_supervisor, timeout):
    return canergy_supervisor(
        *("--nodes", "1-2", "--initial", "10J", "--target", "1J", "--max-grant", "0.5J"),
        *("--response-timeout", timeout),
    )


def committed(status, at_least):
    return all(n["committed"] >= at_least for n in status["nodes"].values())


@pytest.mark.parametrize("fault", FATES)
def test_grants_commit_through_a_faulty_link(
    canergy_bus, canergy_bridge, canergy_supervisor, nodes, timeout, fault
):
    bridge = canergy_bridge(canergy_bus, nodes, seed=43, **{fault: 0.2})
    sup = start(canergy_supervisor, timeout)

    def met() -> bool:  # every direction had frames that met the fault
        return all(d[FATES[fault]] > 0 for d in bridge.status()["directions"].values())

    sup.wait_for(
        lambda s: committed(s, 3) and met(), f"three grants to each node and {FATES[fault]} frames"
    )
    assert sup.grant(2, "0.3J")["outcome"] in ("COMMITTED", "ABORTED")


CUT_END_S = 1.5
"""The link is cut from 0.5 s after the bridge starts until then (the marker's partition)."""


@pytest.mark.canergy(faults="loss=0.1,duplicate=0.1,reorder=0.1,partition=0.5s+1s", seed=7)
def test_grants_resume_after_the_link_is_cut(
    canergy_bus, canergy_bridge, canergy_supervisor, nodes, timeout
):
    bridge = canergy_bridge(canergy_bus, nodes)  # the marker's faults
    sup = start(canergy_supervisor, timeout)

    before = sup.wait_for(lambda s: bridge.status()["uptime_s"] > CUT_END_S, "the end of the cut")
    assert sum(d["partitioned"] for d in bridge.status()["directions"].values()) > 0
    done = {n: s["committed"] for n, s in before["nodes"].items()}
    sup.wait_for(
        lambda s: all(s["nodes"][n]["committed"] >= done[n] + 2 for n in done),
        "two more grants to each node once the link is back",
    )
