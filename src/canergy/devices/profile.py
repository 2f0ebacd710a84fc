"""The device-profile interface: what a guard needs to know of one kind of device.

A guard puts a device under a budget by writing limits to it, reading them back, charging the
power those limits allow (the *envelope*) by the host's clock, and stopping the device before
what is left no longer covers what it may draw until it stands. Everything in that sentence that
depends on the device is here; the rest (the proxy client, the books, when to stop) is
``canergy.devices.guard``, the same for every profile. The I/O side (frames, read-backs, the
stop's frames) is the profile's link in ``canergy.live``; it talks to the guard in the events and
commands below.

- ``Profile.envelope``: the most the device can draw from its supply while it honours ``limits``,
  with the formula's parts (shown in the status);
- ``Profile.closed``: limits under which it can draw nothing (written while it is stopped);
- ``Profile.mismatch``: the limit that did not read back as written, named, or None;
- ``Profile.observe``: figures measured on the device that raise the envelope's parts;
- ``Profile.stop_fw_us``: what the stop itself may draw (0 for a stop that cuts the power
  stage and lets the motor coast).

Writes behind the guard: each profile reads the frames others send its device (its module's
``watch``) into ``LimitsWritten`` (limits whose values the frame carries: charged, written over,
read back), ``Unbounded`` (an effect the guard cannot bound: stopped for good) or nothing; the
guard takes them in ``on_watched``. CiA 402's writes carry objects whose values the guard learns
only by reading the drive back: its profile declares them (``Cia402Profile.watches``), and its
guard charges them at the drive's reach until read back.

``Metering`` names the modes a guard charges in, each with the guarantee the status shows
(``envelope`` and ``counter``: drawn <= granted + bound; ``sampled``: none; a profile device's
guard: one bound per stretch, ``PER_STRETCH``).

How CiA 402 fits: its ``Limits`` (0x6072, 0x6073, 0x6080) are the limits type; ``envelope`` is
``Ratings.envelope_fw`` (τ_max·ω_max + R·i_max²), ``closed`` is ``Limits.closed``, ``mismatch``
compares the three objects read back by SDO, ``stop_fw_us`` is ``Ratings.stop_fw_us`` (quick stop)
or 0 (disable voltage); ``Stop`` is controlword 0x0002 then 0x0000, ``WriteLimits`` an SDO
download and upload of the three objects, feedback the TPDOs with the statusword's power state.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Generic, Protocol, TypeVar

L = TypeVar("L")

SOUND = "drawn <= granted + bound_uj"
"""The guarantee of a sound metering mode (the status's ``guarantee``) where a write behind the
guard opens no stretch of its own (a CiA 402 drive's)."""
PER_STRETCH = "drawn <= granted + stretches * bound_uj"
"""The guarantee of a profile device's guard in a sound mode (``DeviceGuard``): at most one bound
per stretch, the guard's own stop one and each write behind the guard seen one more (a writer
that raises the limits again after the stop runs the device at them until the guard's own are
in force again: the guard writes over it, it cannot silence it). The status's ``stretches``."""


class Metering(Enum):
    """How a guard charges what a device draws, each with its guarantee."""

    ENVELOPE = "envelope"
    """The power the limits written and read back allow, by the host's clock: sound."""
    COUNTER = "counter"
    """A cumulative energy counter's differences (on the device or a meter node), the limits
    bounding only what is drawn past the last reading: sound (CiA 402 only)."""
    SAMPLED = "sampled"
    """The device's own power readings integrated between samples: what happens between two is
    not seen, so no bound and no guarantee."""

    @property
    def sound(self) -> bool:
        return self is not Metering.SAMPLED

    @property
    def guarantee(self) -> str:
        return SOUND if self.sound else "none"


@dataclass(frozen=True, slots=True)
class Envelope:
    """The most a device may draw while it honours some limits, fW (rounded up), and how it is
    made: ``formula`` in words and its ``parts`` in SI units, for the status."""

    fw: int
    formula: str
    parts: dict[str, float]


class Profile(Protocol[L]):
    """One kind of device (see the module doc)."""

    @property
    def name(self) -> str: ...

    def envelope(self, limits: L) -> Envelope: ...

    def closed(self, limits: L) -> L: ...

    def mismatch(self, wrote: L, read: L) -> str | None: ...

    def stop_fw_us(self, limits: L, stop_us: int) -> int: ...

    def fields(self, limits: L) -> dict[str, float]:
        """The limits by name, in SI units (the status's ``limits``)."""
        ...

    def observe(self, measured: dict[str, float]) -> None:
        """Figures the link measured (e.g. ``bus_voltage_v``): the envelope's parts are raised
        to them, never lowered."""
        ...


@dataclass(frozen=True, slots=True)
class LimitsWritten(Generic[L]):
    """A profile's reading of a frame someone else sent the device: it sets the limits to
    ``limits`` (their values are in the frame). Charged at the largest envelope in force with
    them from when it was seen, until limits of the guard's written after it read back; not
    within the guard's deadline: the device is stopped for good."""

    limits: L


@dataclass(frozen=True, slots=True)
class Unbounded:
    """A profile's reading of a frame someone else sent the device: it changes what the
    envelope rests on, and the guard can neither bound nor read back what (the device is
    stopped for good, ``what`` named)."""

    what: str


Foreign = LimitsWritten[L] | Unbounded | None
"""What a write behind the guard is to the bound (None: nothing), as the profile's ``watch``
reads a frame."""


@dataclass(frozen=True, slots=True)
class WriteLimits(Generic[L]):
    """Write ``limits`` to the device and read them back where it can (answer: the guard's
    ``on_limits``)."""

    limits: L
    why: str
    at: int


@dataclass(frozen=True, slots=True)
class ReadLimits:
    """Read the limits back without writing them (answer: the guard's ``on_read``): the periodic
    read-back that finds limits changed where the guard cannot see (an ODrive's USB, say)."""

    why: str
    at: int


@dataclass(frozen=True, slots=True)
class Stop:
    """Stop the device (for an ODrive: Estop and Set_Axis_State IDLE)."""

    why: str
    at: int
