"""python-can's ``virtual`` interface connects only the buses of one process.

A supervisor in one process and a node emulator in another, both on ``-i virtual``, never hear
each other: the supervisor shows every node ``lost`` and the nodes never see a grant, with no
error anywhere. ``alone_on_virtual`` recognises that case (a virtual bus on whose channel no
other bus of this process is open) so that the loop can say why.
"""

from __future__ import annotations

import can

ALONE_AFTER_US = 500_000
"""How long after it starts a loop looks for company on a virtual bus: within its first status
period (1 s by default), after the buses a process opens together are open."""


def alone_on_virtual(bus: can.BusABC) -> str | None:
    """The channel of a python-can virtual bus that no other bus of this process shares (so
    nothing can ever be heard on it); None for any other bus."""
    from can.interfaces import virtual

    inner = getattr(bus, "inner", bus)  # a fault-injecting wrapper (FaultyBus)
    if not isinstance(inner, virtual.VirtualBus):
        return None
    with virtual.channels_lock:
        company = len(virtual.channels.get(inner.channel_id, ())) > 1
    return None if company else str(inner.channel_id)


def explanation(channel: str) -> str:
    """Why nothing is heard on ``channel``, and what to do instead."""
    return (
        f"nothing can be heard on python-can's virtual bus {channel!r}: it connects only buses "
        "of one process, and this process has no other bus on it, so a supervisor or node in "
        "another process is never heard. Run both on SocketCAN (-i socketcan -c vcan0; where the "
        "kernel has no vcan, inside scripts/uml-run), or in one process (canergy demo)"
    )
