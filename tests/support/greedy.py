"""A node host that breaks the rules: node 2 credits every grant twice (energy out of nothing).
The node under test of the tests that check a user's suite fails against a broken node
(tests/test_pytest_plugin.py, tests/test_examples.py)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

from canergy.messages import Message
from firmware_model.node import NodeHost

CHEAT = 2
"""The node that credits twice."""


class Greedy(NodeHost):
    """``NodeHost`` whose node ``CHEAT`` adds to its usable energy again what a message added."""

    def on_message(self, msg: Message, now: int) -> Sequence[Message]:
        before = {n: f.client.state.usable for n, f in self.nodes.items()}
        out = super().on_message(msg, now)
        for n, f in self.nodes.items():
            gained = f.client.state.usable - before[n]
            if gained > 0 and n == CHEAT:
                f.client.state = dataclasses.replace(
                    f.client.state, usable=f.client.state.usable + gained
                )
        return out
