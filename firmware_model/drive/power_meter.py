"""An emulated DC bus power meter: a CANopen node on the drive's bus that meters its energy.

``PowerMeterModel`` is pure (time passed in, integer µs), like ``DriveModel``; its live objects:

- 0x2100 Energy, UNSIGNED16, mJ: ``floor(energy_uj() / 1000) mod 2**16``. It wraps at 65.535 J:
  a reader takes the difference of two readings modulo 2**16 and reads often enough;
- 0x2101 DC voltage, UNSIGNED32, mV: ``voltage_mv()``, or 0 (unknown) without it.

TPDO1 (0x1800: COB-ID 0x180 + node id, transmission type 254, event timer sub 5) maps 0x2100 by
default (0x1A00). ``PowerMeterFace`` is its CANopen side (``canopen_face.NodeFace``: NMT, heartbeat
0x1017, live SDO reads, the TPDO every event timer period in OPERATIONAL).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from firmware_model.drive.canopen_face import NodeFace
from firmware_model.drive.model import NodeModel

__all__ = ["METER_EDS", "PowerMeterFace", "PowerMeterModel"]

METER_EDS = Path(__file__).with_name("power_meter.eds")
"""The emulated power meter's electronic data sheet."""
ENERGY, DC_VOLTAGE = 0x2100, 0x2101


class PowerMeterModel(NodeModel):
    """A power meter reading ``energy_uj()`` (cumulative, µJ) and ``voltage_mv()`` when asked."""

    def __init__(
        self,
        node_id: int,
        energy_uj: Callable[[], int],
        now_us: int = 0,
        *,
        voltage_mv: Callable[[], int] | None = None,
        defaults: Mapping[tuple[int, int], int] | None = None,
        eds: Path = METER_EDS,
    ) -> None:
        super().__init__(node_id, now_us, defaults=defaults, eds=eds)
        self.energy_uj = energy_uj
        self.voltage_mv = voltage_mv

    def _live(self, index: int) -> int | None:
        if index == ENERGY:
            return self.energy_uj() // 1000 % 2**16
        if index == DC_VOLTAGE and self.voltage_mv is not None:
            return max(0, min(2**32 - 1, self.voltage_mv()))
        return None

    def status(self) -> dict[str, Any]:
        return {
            **super().status(),
            "energy_mj": self.read(ENERGY),
            "voltage_mv": self.read(DC_VOLTAGE),
        }


class PowerMeterFace(NodeFace[PowerMeterModel]):
    """One power meter's CANopen side."""

    kind = "power-meter"
