"""How tests read a guard's stop reason."""

from __future__ import annotations


def budget_stop(reason: object) -> bool:
    """Stopped for its budget: spent ("budget exhausted"), or parked ("held: ..."): budget in
    hand below where the guard releases the device, when its bound, grown with the timings
    measured on a loaded machine, reaches above the supervisor's --target
    (``ProxyBooks.parked``)."""
    return isinstance(reason, str) and (reason == "budget exhausted" or reason.startswith("held: "))
