"""A node whose NV record is lost (deleted, both slots corrupted, re-flashed) restarts on the
live stack: it JOINs, is admitted, and never gets back what its earlier life held or spent."""

from __future__ import annotations

from pathlib import Path

import pytest
from support.live_rig import Rig

from canergy.core import Phase
from canergy.messages import Intention
from canergy.units import UJ_PER_J
from firmware_model.nvstore import SLOT_SIZE

NODE = 5


def _lose_record(path: Path, how: str) -> None:
    if how == "deleted":
        path.unlink()
    else:  # one bit flipped in each slot: both CRCs fail
        raw = bytearray(path.read_bytes())
        raw[10] ^= 0x01
        raw[SLOT_SIZE + 10] ^= 0x01
        path.write_bytes(bytes(raw))


@pytest.mark.parametrize("how", ["deleted", "both slots corrupted"])
def test_a_node_that_lost_its_record_is_paid_nothing_of_its_past(tmp_path: Path, how: str) -> None:
    rig = Rig(tmp_path, [NODE], power_w=0.5, target=UJ_PER_J, max_grant=UJ_PER_J // 2)
    try:
        service = rig.start_supervisor()
        host = rig.start_clients()
        rig.wait(lambda: rig.committed(NODE) >= 4)
        rig.power_loss_clients(host)
        old = host.nodes[NODE]
        held_before = old.client.state.usable + old.actuator.drawn_uj
        _lose_record(tmp_path / f"node-{NODE}.nv", how)

        new = rig.start_clients().nodes[NODE]
        assert new.joins == 1  # no valid record at start: it announced itself
        rig.wait(lambda: service.nodes[NODE].admitted >= 1 and not new.joining)
        committed_at_admission = rig.committed(NODE)
        rig.wait(lambda: rig.committed(NODE) >= committed_at_admission + 2)
        rig.settle()

        session = service.core.session(NODE)
        released = session.delivered - session.returned  # all the supervisor ever let go
        used_and_held = held_before + new.actuator.drawn_uj + new.client.state.usable
        assert used_and_held <= released, (used_and_held, released)
        assert new.status()["joins"] == 1 and new.client.state.credited_unknown is False
        assert rig.ledger().dissipated >= 0
    finally:
        rig.close()


def test_a_replayed_intention_moves_nothing_after_admission(tmp_path: Path) -> None:
    """A capture of the node's earlier life played back at it after it rejoined."""
    rig = Rig(tmp_path, [NODE], power_w=0.0, target=UJ_PER_J, max_grant=UJ_PER_J // 2)
    try:
        service = rig.start_supervisor()
        host = rig.start_clients()
        rig.wait(lambda: rig.committed(NODE) >= 2)
        first = service.core.session(NODE)
        rig.settle()
        rig.power_loss_clients(host)
        (tmp_path / f"node-{NODE}.nv").unlink()
        service = rig.start_supervisor()
        host = rig.start_clients()
        new = host.nodes[NODE]
        rig.wait(lambda: not new.joining and new.client.state.phase is Phase.IDLE)
        rig.settle()
        rig.power_loss_clients(host)  # its loop stopped: the test thread alone drives it
        level = new.client.state.usable
        for tx in range(1, first.tx + 1):  # every intention of the earlier life, Gs and all
            replay = Intention(NODE, tx, 500, first.delivered // 1000)
            assert new.on_message(replay, 0) == []
        assert new.client.state.usable == level
    finally:
        rig.close()


pytestmark = pytest.mark.usefixtures("both_cores")
"""Each test on the Python core and on the compiled one (tests/conftest.py)."""
