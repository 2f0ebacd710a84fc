"""A device's own watchdog, read back rather than hoped for. Sans-IO.

While the supervisor runs, its guard bounds what a device draws. When the supervisor dies the
device holds the limits (ODrive) or the command (Damiao MIT motor) last in force, unguarded: only
its own watchdog (ODrive ``axis.config.enable_watchdog`` and ``watchdog_timeout``; Damiao's
``CAN Timeout`` register) or a relay on its supply stops it. The guard reads the watchdog at
set-up and with every periodic read-back of the limits, judges it against a longest timeout, and
the status states what follows: ``after_exit_uj``, the envelope the guard let the device run at
times the watchdog's timeout, or ``unbounded`` (the watchdog off, not read, or the device has
none).

That product bounds only what the device draws once nothing feeds its watchdog: an ODrive's is
fed by the frames it receives (the application's setpoints), so an application that goes on
commanding the axis after the supervisor died keeps it running at the last limits. The status's
``after_exit`` says so.

Policy (``WatchdogPolicy``): a watchdog that reads off, longer than ``max_us``, or does not answer
refuses the device unless ``allow`` (an explicit flag, as ``--odrive-trust-limits`` is for
limits); then it is reported (the status's ``problem``, a line on stderr). A watchdog that is not
read at all (no endpoint ids given) is reported, never refused. A periodic read-back that shows
another watchdog than the last one read (changed behind the guard, over USB or UART) counts in
``changes``; one the policy would refuse stops the device for good. A periodic read-back left
unanswered stops the device too: the ODrive guard's through its limits' read-back (unanswered
with it), the MIT gate's, which reads the watchdog alone (``alone``), here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from canergy.cia402.envelope import ceil_div
from canergy.cia402.meter import FW_US_PER_UJ

ARMED, OFF, TOO_LONG, UNANSWERED, UNREAD, NONE = (
    "armed",
    "off",
    "too long",
    "unanswered",
    "not read",
    "none",
)
"""The status's ``state``."""
FED_BY = (
    "the envelope times the timeout, counted from the last frame that fed the watchdog (an "
    "application that goes on commanding the device after the supervisor died keeps it fed)"
)


@dataclass(frozen=True, slots=True)
class WatchdogReading:
    """What the device holds: its watchdog armed or not, and its timeout."""

    enabled: bool
    timeout_s: float

    @property
    def timeout_us(self) -> int | None:
        """The timeout in µs, rounded up (None: not a finite positive number)."""
        if not math.isfinite(self.timeout_s) or self.timeout_s <= 0:
            return None
        return math.ceil(self.timeout_s * 1e6)


@dataclass(frozen=True, slots=True)
class WatchdogPolicy:
    """How a guard judges its device's watchdog."""

    kind: str
    """What the watchdog is on this device (``odrive axis.config.enable_watchdog``...)."""
    read: bool = True
    """The link reads it (False: ``unread`` says why; reported, not refused)."""
    max_us: int = 1_000_000
    """The longest timeout taken without ``allow``."""
    allow: bool = False
    """Take a watchdog that reads off, too long or unanswered (reported) instead of refusing."""
    allow_flag: str = "--odrive-allow-unwatched"
    remedy: str = "accept it with --odrive-allow-unwatched"
    """What the refusal tells the user to do."""
    unread: str = ""
    """Why it is not read (``read`` False), for the status and stderr."""
    exists: bool = True
    """False: the device has no watchdog at all (CubeMars AK): ``state`` none."""


def problem(policy: WatchdogPolicy, reading: WatchdogReading | None) -> str | None:
    """What keeps ``reading`` from bounding what the device draws after the supervisor died
    (None: armed within ``max_us``)."""
    if reading is None:
        return "not read back (the device did not answer)"
    if not reading.enabled or reading.timeout_us is None:
        what = "disabled" if not reading.enabled else f"timeout {reading.timeout_s:g} s"
        return f"off ({what})"
    if reading.timeout_us > policy.max_us:
        return f"timeout {reading.timeout_s:g} s, longer than {policy.max_us / 1e6:g} s"
    return None


def _state(reading: WatchdogReading | None, why: str | None) -> str:
    if why is None:
        return ARMED
    if reading is None:
        return UNANSWERED
    return OFF if why.startswith("off") else TOO_LONG


class WatchdogCheck:
    """The guard's record of its device's watchdog (``DeviceGuard.watchdog``)."""

    def __init__(self, policy: WatchdogPolicy) -> None:
        self.policy = policy
        self.reading: WatchdogReading | None = None
        self.read_at: int | None = None
        """When it last read back (None: never)."""
        self.asked = False
        """The set-up's read happened (answered or not)."""
        self.problem: str | None = None
        self.changes = 0
        """Periodic read-backs that showed another watchdog than the one read before."""
        self.refusal: str | None = None
        """Why the device was refused for its watchdog (said on stderr by ``note``)."""
        self.reads = 0
        """Read-backs answered (the set-up's and the periodic ones)."""

    def take(
        self, now: int, reading: WatchdogReading | None, periodic: bool, alone: bool = False
    ) -> str | None:
        """A read-back (None: unanswered); the reason to refuse the device, if the policy
        does. ``alone``: the periodic read-back reads the watchdog alone (no limits read with
        it whose silence stops the device): unanswered, it refuses the device itself."""
        p = self.policy
        if periodic and reading is None and not alone:
            return None  # the limits' read-back is unanswered too: the guard stops it for that
        changed = periodic and self.asked and reading is not None and reading != self.reading
        before = self.reading
        self.asked = True
        self.reading = reading
        if reading is not None:
            self.read_at = now
            self.reads += 1
        self.problem = problem(p, reading)
        if changed:
            self.changes += 1
        if self.problem is None or p.allow:
            return None
        if periodic and reading is None:
            self.refusal = f"watchdog not read back: a periodic read-back unanswered ({p.kind})"
        elif changed:
            was = "not read" if before is None else describe(before)
            self.refusal = (
                f"watchdog changed behind the guard (a periodic read-back): {self.problem}, "
                f"was {was}"
            )
        else:
            self.refusal = f"watchdog {self.problem} ({p.kind}); {p.remedy}"
        return self.refusal

    def note(self) -> str | None:
        """A line for stderr when the device was refused for its watchdog, or a watchdog read
        leaves it unbounded after the supervisor's exit and the policy takes it (None: nothing
        to say)."""
        p = self.policy
        if self.refusal is not None:
            return f"refused: {self.refusal}"
        if not p.exists or not p.read:
            return None  # said once for all the devices where the flags are read
        if self.problem is None or not p.allow or not self.asked:
            return None
        after = (
            "after the supervisor's exit it may draw its envelope times that timeout"
            if _state(self.reading, self.problem) == TOO_LONG
            else "after the supervisor's exit unbounded"
        )
        return f"watchdog {self.problem}, accepted ({p.allow_flag}): {after}"

    def status(self, envelope_fw: int | None, now: int | None = None) -> dict[str, object]:
        """The status's ``watchdog``; ``envelope_fw``: the most the guard lets the device run
        at (its full limits; None: no envelope, sampled metering); ``now``: for the age of the
        last answered read-back (``verified_age_us``)."""
        p = self.policy
        r = self.reading
        if not p.exists:
            state = NONE
        elif not p.read:
            state = UNREAD
        elif not self.asked:
            state = "not read yet"
        else:
            state = _state(r, self.problem)
        after: int | None = None
        armed = state in (ARMED, TOO_LONG) and envelope_fw is not None
        if armed and r is not None and r.timeout_us is not None:
            after = ceil_div((envelope_fw or 0) * r.timeout_us, FW_US_PER_UJ)
        return {
            "kind": p.kind,
            "state": state,
            "enabled": None if r is None else r.enabled,
            "timeout_s": None if r is None else r.timeout_s,
            "verified": r is not None,
            "max_s": p.max_us / 1e6,
            "problem": p.unread if state == UNREAD else self.problem,
            "accepted": p.allow if self.problem is not None else None,
            "changes": self.changes,
            "reads": self.reads,
            "verified_age_us": None
            if self.read_at is None or now is None
            else max(0, now - self.read_at),
            "after_exit_uj": after,
            "after_exit": FED_BY if after is not None else "unbounded",
        }


def describe(reading: WatchdogReading) -> str:
    state = "enabled" if reading.enabled else "disabled"
    return f"{state}, timeout {reading.timeout_s:g} s"
