"""The emulated nodes as CANopen slaves (python-canopen ``LocalNode``s) on the same bus.

Each node boots (boot-up message, PRE-OPERATIONAL), produces a heartbeat (0x1017) and serves SDO
reads of its energy objects (canergy's ``canergy_node.eds``, 0x2000-0x2007, read-only, live
values) and writes of its parameters (0x2100-0x2102). NMT gates the protocol: only OPERATIONAL
accepts an INTENTION; PRE-OPERATIONAL and STOPPED leave it unanswered (the supervisor does not
grant to such a node, and one already on its way ends as a write-off that the next intention pays
back), and STOPPED halts the actuator.

canopen and canergy share one bus and one ``can.Notifier``: canopen's listeners plus a
``can.BufferedReader`` the canergy loop reads from. Those pieces and the EDS belong to
``canergy.live.canopen.shared_bus`` (the supervisor uses them too).
"""

from __future__ import annotations

from typing import Any

import canopen

from canergy.live.canopen.shared_bus import EDS
from firmware_model.node import PARAM_INDEXES, FirmwareNode

__all__ = ["CanopenFace"]


class CanopenFace:
    """One firmware node's CANopen side."""

    def __init__(self, node: FirmwareNode, network: canopen.Network) -> None:
        self.node = node
        self.local = canopen.LocalNode(node.node, str(EDS))
        self.local.add_read_callback(self._read)
        self.local.add_write_callback(self._write)
        network.add_node(self.local)
        node.gate = lambda: self.local.nmt.state

    def boot(self) -> None:
        """Boot-up message, then PRE-OPERATIONAL with the heartbeat running.

        A master may answer the boot-up with NMT start before the second step runs; python-canopen
        then skips starting the heartbeat, so it is started here in any case (and a master that
        sees PRE-OPERATIONAL starts the node again).
        """
        self.local.nmt.send_command(0x81)  # reset node: INITIALISING, boot-up message
        self.local.nmt.send_command(0x80)  # enter PRE-OPERATIONAL
        period = self.local.sdo[0x1017]
        assert isinstance(period, canopen.sdo.base.SdoVariable)
        self.local.nmt.start_heartbeat(int(period.raw))

    def _read(self, index: int, subindex: int, od: Any) -> int | None:
        c, n = self.node.client.state, self.node
        values = {
            0x2000: c.usable,
            0x2001: c.spent,
            0x2002: c.credited,
            0x2003: c.last_tx,
            0x2004: c.return_seq,
            0x2005: c.return_pending,
            0x2006: int(n.actuator.halted),
            0x2007: n.decode_errors,
            **dict(zip(PARAM_INDEXES, n.parameters(), strict=True)),
        }
        return values.get(index)

    def _write(self, index: int, subindex: int, od: Any, data: bytes) -> None:
        value = int.from_bytes(data, "little")
        self.node.set_parameter(index, value)
