"""``--on-stuck CMD``: the operator's last resort when a guarded device does not obey its stop.

A device that keeps moving or drawing current after its stop, or whose feedback is gone, is
STUCK (``canergy.devices.guard``): the guard repeats the stop, but nothing on the bus can make a
device that ignores its frames stop. Benches cut the actuator's supply with a relay or a power
distribution unit; ``OnStuck`` runs the command that does it, once each time a device becomes
STUCK (not again while it stays so), without waiting for it: the loop goes on repeating the stop
and booking what the device may draw as uncontained.

The command is split as a shell would (``shlex``) but run without one. ``{node}`` and
``{profile}`` in it are replaced, and the environment carries ``CANERGY_STUCK_NODE``,
``CANERGY_STUCK_PROFILE`` and ``CANERGY_STUCK_REASON``. Its start and its exit status are told
on the report line (stderr); a command that cannot start is told, never raised into the loop.

``DeviceNews`` is what a host says of its guarded devices, the one piece the supervisor (its
ODrive axes, moteus controllers and hosted MIT motors) and ``MitBus`` (``canergy inline``) use:
a line when a device's phase or stop reason changes, a STUCK one as such, and ``OnStuck`` called.
"""

from __future__ import annotations

import os
import shlex
import subprocess
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from canergy.devices.guard import DeviceGuard


class OnStuckError(ValueError):
    """``--on-stuck`` that cannot be a command line (an empty one, an unclosed quote)."""


def parse_on_stuck(text: str) -> str:
    """The argparse type of ``--on-stuck``: a command line ``shlex`` can split, not empty."""
    try:
        words = shlex.split(text)
    except ValueError as exc:
        raise OnStuckError(f"not a command line: {exc}") from None
    if not words:
        raise OnStuckError("an empty command")
    return text


@dataclass(slots=True)
class Run:
    """One run of the command: for whom, and how it ended (None while it runs)."""

    node: int
    profile: str
    reason: str
    pid: int | None = None
    exit_code: int | None = None
    error: str | None = None


class OnStuck:
    """Runs ``command`` once per STUCK episode of each device (``__call__`` on every pass with
    the device's ``stuck`` reason; None clears the episode)."""

    def __init__(
        self,
        command: str,
        report: Callable[[str], None],
        *,
        spawn: Callable[..., Any] = subprocess.Popen,
    ) -> None:
        self.command = parse_on_stuck(command)
        self.report = report
        self.spawn = spawn
        self.runs: list[Run] = []
        self._stuck: dict[int, str] = {}
        self._lock = threading.Lock()

    def __call__(self, profile: str, node: int, stuck: str | None) -> None:
        if stuck is None:
            self._stuck.pop(node, None)
            return
        if node in self._stuck:
            return
        self._stuck[node] = stuck
        self._start(Run(node, profile, stuck))

    def _start(self, run: Run) -> None:
        words = [w.replace("{node}", str(run.node)) for w in shlex.split(self.command)]
        words = [w.replace("{profile}", run.profile) for w in words]
        env = {
            **os.environ,
            "CANERGY_STUCK_NODE": str(run.node),
            "CANERGY_STUCK_PROFILE": run.profile,
            "CANERGY_STUCK_REASON": run.reason,
        }
        with self._lock:
            self.runs.append(run)
        what = f"{run.profile} {run.node}"
        try:
            proc = self.spawn(words, env=env, stdin=subprocess.DEVNULL)
        except OSError as exc:
            run.error = f"{words[0]}: {exc.strerror or exc}"
            self.report(f"--on-stuck for {what} could not start: {run.error}")
            return
        run.pid = proc.pid
        self.report(f"--on-stuck for {what}: started {shlex.join(words)} (pid {proc.pid})")
        threading.Thread(target=self._wait, args=(run, proc), daemon=True).start()

    def _wait(self, run: Run, proc: Any) -> None:
        code = proc.wait()
        with self._lock:
            run.exit_code = code
        if code:
            self.report(f"--on-stuck for {run.profile} {run.node} exited {code}")

    def status(self, node: int) -> dict[str, Any] | None:
        """The last run for ``node`` (the device status's ``on_stuck``), None if none ran."""
        with self._lock:
            mine = [r for r in self.runs if r.node == node]
            if not mine:
                return None
            last = mine[-1]
            return {
                "runs": len(mine),
                "reason": last.reason,
                "pid": last.pid,
                "exit_code": last.exit_code,
                "error": last.error,
            }


class DeviceNews:
    """Call on every pass with each guarded device: ``report`` gets a line when its phase or
    stop reason changes (``mit motor 1: STUCK (...; stop repeated; 0.123 J left)``), and
    ``on_stuck`` (``--on-stuck``) is told its ``stuck`` reason."""

    def __init__(
        self,
        report: Callable[[str], None] | None,
        on_stuck: OnStuck | None,
        ident: Callable[[DeviceGuard[Any]], int] | None = None,
    ) -> None:
        """``ident``: the number a device goes by (default: its guard's node id; ``MitBus``:
        the motor's CAN id, its proxy's node id being another)."""
        self.report = report
        self.on_stuck = on_stuck
        self.ident = ident or (lambda guard: guard.node)
        self.said: dict[int, tuple[str, str | None]] = {}
        self.watchdog_said: dict[int, str | None] = {}

    def __call__(self, guard: DeviceGuard[Any]) -> None:
        stuck = guard.stuck
        number = self.ident(guard)
        if self.on_stuck is not None:
            self.on_stuck(guard.profile.name, number, stuck)
        self._watchdog(guard, number)
        seen = (guard.phase.value, guard.stop_reason if stuck is None else stuck)
        if self.report is None or self.said.setdefault(number, seen) == seen:
            return
        self.said[number] = seen
        left = f"{guard.usable / 1e6:.3f} J left"
        noun = "motor" if guard.profile.name == "mit" else "axis"
        what = f"{guard.profile.name} {noun} {number}"
        if stuck is not None:
            self.report(f"{what}: STUCK ({stuck}; stop repeated; {left})")
        elif guard.stop_reason is None:
            self.report(f"{what}: released ({left})")
        else:
            self.report(f"{what}: {guard.phase.value} ({guard.stop_reason}; {left})")

    def _watchdog(self, guard: DeviceGuard[Any], number: int) -> None:
        """A line when the device's watchdog, read, leaves it unbounded after the exit and
        the policy took it (``WatchdogCheck.note``), once per change."""
        note = None if guard.watchdog is None else guard.watchdog.note()
        if self.report is None or self.watchdog_said.get(number) == note:
            return
        self.watchdog_said[number] = note
        if note is not None:
            noun = "motor" if guard.profile.name == "mit" else "axis"
            self.report(f"{guard.profile.name} {noun} {number}: {note}")
