"""The gateway's upstream role under the witnessed rules (``Gateway(up_variant="witnessed")``):
forwarding is a draw the supervisor above acknowledges before anything goes below, every start is
a RESUME it confirms before anything is granted below, and a record restored from an older copy
creates nothing (the hardened upstream rules create what the gateway returned after the copy)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import pytest

from canergy.core import Action, ClientState, Persist, Send, Supervisor
from canergy.core.errors import LocalProtocolError
from canergy.core.gateway import Gateway, link_gap
from canergy.core.witnessed import CLIENT
from canergy.ledger import TreeLedger, ledger
from canergy.live.gateway_state import load_gateway, save_gateway
from canergy.live.state_file import StateFileError
from canergy.messages import Debit, ReturnAck, ToClient

GW = 20
J = 1_000_000


class Pair:
    """A root supervisor and a gateway under ``variant`` above, frames delivered at once."""

    def __init__(self, variant: str) -> None:
        self.variant = variant
        self.root = Supervisor([GW], 10 * J, variant=variant)
        self.gw = self.gateway()
        self.pump(self.gw.books_lost(7, 0))

    def gateway(self, state: object = None) -> Gateway:
        return Gateway(GW, [1], up_variant=self.variant, state=state)  # type: ignore[arg-type]

    def pump(self, actions: Sequence[Action]) -> None:
        queue = [a.message for a in actions if isinstance(a, Send)]
        while queue:
            msg = queue.pop(0)
            if isinstance(msg, ToClient):
                answers = self.gw.receive_upstream(msg, 0)
            else:
                answers = self.root.receive(msg, 0)  # type: ignore[arg-type]
            queue += [a.message for a in answers if isinstance(a, Send)]

    def grant(self, uj: int) -> None:
        self.pump(self.root.begin(GW, uj, 0))
        self.pump(self.root.commit(GW, 0))

    def tree(self) -> TreeLedger:
        return TreeLedger(
            {
                "root": ledger(self.root.state, [self.gw.up.state]),
                "gateway": ledger(self.gw.down.state, [ClientState(1)]),
            },
            {"gateway": link_gap(self.gw.up.state, self.gw.down.state)},
        )


def test_forwarding_is_a_draw_acknowledged_above_before_anything_goes_below() -> None:
    p = Pair("witnessed")
    p.pump(p.root.begin(GW, 2 * J, 0))
    commit = [a.message for a in p.root.commit(GW, 0) if isinstance(a, Send)]
    acts = p.gw.receive_upstream(commit[0], 0)  # type: ignore[arg-type]
    draws = [a.message for a in acts if isinstance(a, Send) and isinstance(a.message, Debit)]
    assert acts[0] == Persist() and len(draws) == 1 and draws[0].amount_mj == 2000
    up = p.gw.up.state
    assert up.pending_draw and up.return_pending == 2 * J and up.usable == 0
    assert p.gw.down.state.usable == 0  # nothing below before the acknowledgement
    assert link_gap(up, p.gw.down.state) == 0
    acts = p.gw.receive_upstream(ReturnAck(GW, draws[0].seq), 0)
    assert acts[0] == Persist()
    assert p.gw.down.state.usable == 2 * J == p.gw.down.state.injected == p.gw.up.state.spent
    assert link_gap(p.gw.up.state, p.gw.down.state) == 0


@pytest.mark.parametrize("variant", ["hardened", "witnessed"])
def test_an_older_copy_of_the_gateway_creates_energy_only_under_hardened(variant: str) -> None:
    """3 J forwarded, the record copied, 2 J returned upstream, the copy started again."""
    p = Pair(variant)
    p.grant(3 * J)
    copy = p.gw.state
    p.pump(p.gw.give_back(2 * J, 0))
    assert p.root.session(GW).returned == 2 * J
    p.gw = p.gateway(copy)
    resumed = p.gw.power_loss(0, 0x1234, 0x77)
    if variant == "hardened":
        assert p.gw.upstream_waiting() is None and p.gw.down.state.usable == 3 * J
        assert not p.tree().passive  # 2 J created: below again, and credited above
        return
    assert p.gw.upstream_waiting() is not None
    with pytest.raises(LocalProtocolError, match="no grant below until the supervisor above"):
        p.gw.down.begin(1, J, 0)
    with pytest.raises(LocalProtocolError):  # nor a return upstream
        p.gw.give_back(J, 0)
    p.pump(resumed)  # RESUME: the root holds a later debit: behind
    assert p.gw.upstream_waiting() is None and p.gw.behind == 1 and p.gw.dropped == 3 * J
    assert p.gw.down.state.usable == 0 and p.gw.up.state.usable == 0
    assert p.tree().passive, p.tree().as_json()


def test_a_confirmed_start_keeps_the_books_and_forwards_what_was_waiting() -> None:
    """A restart from the current record: confirmed, nothing dropped; a credit that was waiting
    for its draw is drawn once confirmed."""
    p = Pair("witnessed")
    p.grant(J)
    p.gw = p.gateway(p.gw.state)
    p.pump(p.gw.power_loss(0, 0x4321))
    assert p.gw.behind == 0 and p.gw.down.state.usable == J and p.gw.upstream_waiting() is None
    p.pump(p.gw.down.begin(1, J // 2, 0))  # grants below go on
    assert p.gw.down.state.usable == J // 2 and p.tree().passive


def test_a_restored_copy_with_its_draw_pending_is_confirmed_and_the_draw_dropped() -> None:
    """Copied between the DRAW's write and its acknowledgement: the root holds that debit, so the
    copy is current; the draw, released once already, is dropped unreleased."""
    p = Pair("witnessed")
    p.pump(p.root.begin(GW, J, 0))
    commit = [a.message for a in p.root.commit(GW, 0) if isinstance(a, Send)]
    acts = p.gw.receive_upstream(commit[0], 0)  # type: ignore[arg-type]
    copy = p.gw.state
    assert copy.up.pending_draw
    p.pump(acts)  # the draw goes above, is acknowledged, and J goes below
    assert p.gw.down.state.usable == J
    p.gw = p.gateway(copy)
    p.pump(p.gw.power_loss(0, 0x999))
    assert p.gw.behind == 0 and p.gw.up.state.return_pending == 0
    assert p.gw.down.state.usable == 0 and p.tree().passive


def test_the_state_file_keeps_a_pending_draw_and_the_upstream_rules(tmp_path: Path) -> None:
    p = Pair("witnessed")
    p.pump(p.root.begin(GW, J, 0))
    commit = [a.message for a in p.root.commit(GW, 0) if isinstance(a, Send)]
    p.gw.receive_upstream(commit[0], 0)  # type: ignore[arg-type]
    path = tmp_path / "gw.json"
    save_gateway(path, p.gw.state, "hardened", fsync=False, up_variant="witnessed")
    loaded = load_gateway(path, "hardened", GW, (1,), up_variant="witnessed")
    assert loaded.up.pending_draw and CLIENT.persistent(loaded.up) == CLIENT.persistent(
        p.gw.up.state
    )
    with pytest.raises(StateFileError, match="upstream variant 'witnessed', not 'hardened'"):
        load_gateway(path, "hardened", GW, (1,))
    text = path.read_text().replace('"pending_draw":1', '"pending_draw":2')
    path.write_text(text)
    with pytest.raises(StateFileError, match="pending_draw"):
        load_gateway(path, "hardened", GW, (1,), up_variant="witnessed", accept_edited=True)


def test_both_legs_witnessed_a_start_waits_above_and_below() -> None:
    """``variant="witnessed"`` below too: a start sends RESUME above and SYNC below; nothing is
    granted below until both are answered (the reason names the wait above first)."""
    p = Pair("witnessed")
    p.grant(J)
    gw = Gateway(GW, [1], variant="witnessed", up_variant="witnessed", state=p.gw.state)
    p.gw = gw
    resumed = gw.power_loss(0, 0x55, 0x66)
    assert gw.down.unconfirmed() == (1,) and gw.upstream_waiting() is not None
    with pytest.raises(LocalProtocolError, match="supervisor above"):
        gw.down.begin(1, J // 2, 0)
    p.pump(resumed)  # confirmed above; below still waits for node 1's books
    assert gw.upstream_waiting() is None and gw.behind == 0 and gw.down.state.usable == J
    with pytest.raises(LocalProtocolError, match="waiting for node"):
        gw.down.begin(1, J // 2, 0)
