"""A node host whose nodes decide by the C client library (firmware/'s rules, through cffi)
instead of the Python client: the emulator's actuator, NV file and bus loop around C's
decisions. ``BrokenCHost`` runs the ``broken`` build, where a repeated COMMIT is credited again:
the pytest plugin's books must fail naming the node (tests/test_plugin_c_node.py)."""

from __future__ import annotations

from collections.abc import Sequence

from canergy.core import Action
from canergy.core.variants import VARIANTS
from firmware_model.node import FirmwareNode, NodeHost
from support.c_binding import CClient, library


class _Client(CClient):
    """``CClient`` with the rest of ``canergy.core.Client``'s interface the emulator's node
    uses: its rules and ``spend`` at a time (the hardened rules spend at once)."""

    variant = VARIANTS["hardened"]

    def spend(self, amount: int, now: int = 0) -> list[Action]:  # type: ignore[override]
        return super().spend(amount)

    def can_spend(self) -> bool:
        return True


class CHost(NodeHost):
    """``NodeHost`` whose nodes' clients are the C library's (``build``: its variant, ``""``
    the tests' UBSan build), each taking over the record its node started from."""

    build = ""

    def __init__(self, nodes: Sequence[FirmwareNode]) -> None:
        lib = library(self.build)
        for fw in nodes:
            fw.client = _Client(fw.node, timing=fw.client.timing, state=fw.client.state, lib=lib)
        super().__init__(nodes)


class BrokenCHost(CHost):
    """The ``broken`` build: a COMMIT repeated for the transaction already resolved is credited
    a second time."""

    build = "broken"
