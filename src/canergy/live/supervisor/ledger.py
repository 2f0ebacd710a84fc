"""The books as one run of the supervisor sees them: what it granted since its start, each node's
share, an injection into the budget, and their writing (``outputs.BooksOut``): at the start, and
then once per step in which the core's persistent record changed (``dirty``), before the
step's frames leave (the service says when a step ends: ``save_if_dirty``)."""

from __future__ import annotations

from canergy.core.supervisor import SupervisorCore
from canergy.live.supervisor.outputs import BooksOut
from canergy.live.supervisor.state_file import ENERGY_MAX_UJ
from canergy.units import format_energy


class Ledger:
    """``core``'s books for this run, written through ``out``; ``listen_only``: a run that keeps
    no books of its own (an injection is refused)."""

    def __init__(self, core: SupervisorCore, out: BooksOut, *, listen_only: bool) -> None:
        self.core = core
        self.out = out
        self.write = out.write
        """Write the books now (``BooksOut.write``, called as it is: no call more per save)."""
        self.listen_only = listen_only
        self.delivered_at_start = sum(s.delivered for s in core.state.sessions)
        self.injected_this_run = 0
        """Energy this run added to Us (``inject``), µJ."""
        self.dirty = False
        """The core's persistent record changed since the books were last written (the
        service sets it for each ``Persist`` action)."""

    def open(self, inject_uj: int) -> None:
        """The run's start: ``inject_uj`` µJ injected (0: none; ``inject``), and the books
        written (not listen-only), so an injection is on disk before anything is granted."""
        if inject_uj:
            self.inject(inject_uj)
        if not self.listen_only:
            self.write()

    def save_if_dirty(self) -> None:
        """A step ends: the books written if the record changed in it."""
        if self.dirty:
            self.write()
            self.dirty = False

    def inject(self, amount: int) -> None:
        """Add ``amount`` µJ to Us, counted as injected (``--inject``): refused (``ValueError``)
        listen-only, for nothing, or past ``ENERGY_MAX_UJ``. ``open`` writes the books next."""
        if self.listen_only:
            raise ValueError("--inject needs a supervisor that writes its state: not --listen-only")
        st = self.core.state
        if amount <= 0 or st.initial + st.injected + amount > ENERGY_MAX_UJ:
            raise ValueError(
                f"--inject {format_energy(amount)}: must be more than 0 and keep initial + "
                f"injected at most {ENERGY_MAX_UJ} µJ"
            )
        self.core.inject(amount)
        self.injected_this_run = amount

    def granted_total(self) -> int:
        """Energy committed, written off or reserved since start (the books, not telemetry)."""
        st = self.core.state
        return sum(s.delivered + s.reserved for s in st.sessions) - self.delivered_at_start

    def books(self) -> dict[int, dict[str, int]]:
        """Per node what the books released and got back (a consistent snapshot)."""
        return {
            s.node: {
                "delivered_uj": s.delivered,
                "reserved_uj": s.reserved,
                "returned_uj": s.returned,
            }
            for s in self.core.state.sessions
        }

    @property
    def saves(self) -> int:
        """Times the books were written (the state file, or the caller's save)."""
        return self.out.saves
