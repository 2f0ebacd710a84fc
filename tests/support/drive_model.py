"""The emulated CiA 402 drive without CAN, for tests in virtual time: a drive already enabled.

``enabled`` is a ``DriveModel`` in OPERATION ENABLED at t = 1 ms (``MS`` µs), driven there
through the controlword as a master would, on node ``NODE``.
"""

from __future__ import annotations

from firmware_model.drive.model import DriveModel
from firmware_model.drive.motor import LoadTorque

NODE = 10
MS = 1000


def enabled(objects: dict[int, int] | None = None, mode: int = 3) -> DriveModel:
    """A drive in OPERATION ENABLED at t = 1 ms in ``mode``, with ``objects`` written first."""
    m = DriveModel(NODE, load=LoadTorque.constant(0.02, opposing=True))
    m.advance(MS)
    m.write(0x6060, 0, mode)
    for index, value in (objects or {}).items():
        m.write(index, 0, value)
    for cw in (0x06, 0x07, 0x0F):
        m.write(0x6040, 0, cw)
    assert m.state == "OPERATION ENABLED"
    return m
