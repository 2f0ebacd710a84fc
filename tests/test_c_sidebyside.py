"""The Python hardened client and the C client side by side, under the same events: the machine
of ``support.side_by_side`` (200 examples of 60 steps by default; ``CANERGY_LONG=1`` runs 2,500
of 120). After every step both clients must have sent the same frames byte for byte, asked for
the same persist, hold the same NV image byte for byte and the same state and energy counters.
"""

from __future__ import annotations

from support.side_by_side import SETTINGS, SideBySide

TestSideBySide = SideBySide.TestCase
TestSideBySide.settings = SETTINGS
