"""canergy's optional parts, and the one line a command says when the part it needs is missing.

``pip install canergy`` holds what ``supervisor``, ``grant``, ``dump``, ``decode``, ``audit``,
``check``, ``demo`` and the other commands without a figure need. Two parts are extras:

- ``canergy[plot]`` (matplotlib): ``plot``, ``simulate``, ``sweep`` and ``rules --docs``, which
  draw figures;
- ``canergy[zenoh]`` (eclipse-zenoh): the ``zenoh`` python-can interface (``-i zenoh``,
  ``--upstream-interface zenoh``);
- ``canergy[prove]`` (z3-solver): ``prove``, the passivity theorem checked by z3
  (``canergy.prove``).

``canergy[all]`` is both. A command that needs a missing extra checks before it does any work
and exits 2 with one line, e.g. ``canergy plot: needs matplotlib: pip install 'canergy[plot]'``;
opening ``-i zenoh`` without eclipse-zenoh fails through the bus-open error with the same advice.
Every other canergy module imports without the extras; those in ``NEEDS_EXTRA`` raise
``MissingExtra`` when imported without theirs (the commands import them only when they draw).
"""

from __future__ import annotations

import importlib

EXTRAS: dict[str, tuple[str, str]] = {
    "plot": ("matplotlib", "matplotlib"),
    "zenoh": ("zenoh", "eclipse-zenoh"),
    "prove": ("z3", "z3-solver"),
}
"""Extra -> (the module it brings, the distribution ``pip`` installs)."""

NEEDS_EXTRA: dict[str, str] = {
    "canergy.inspect.capture_plot": "plot",
    "canergy.live.transports.zenoh_bus": "zenoh",
    "canergy.prove.invariant": "prove",
    "canergy.prove.obligations": "prove",
    "canergy.prove.rules": "prove",
    "canergy.prove.steps": "prove",
    "canergy.prove.symbolic": "prove",
    "canergy.prove.world": "prove",
    "canergy.prove.witnessed": "prove",
    "canergy.prove.witnessed_proof": "prove",
    "canergy.sequence_chart": "plot",
    "canergy.sim.figures": "plot",
}
"""The canergy modules that cannot be imported without an extra, and which one."""


class MissingExtra(ImportError):
    """An extra is not installed: the message names it and how to install it."""

    def __init__(self, extra: str, cause: ImportError | None = None) -> None:
        module, distribution = EXTRAS[extra]
        text = f"needs {distribution}: pip install 'canergy[{extra}]'"
        missing = cause.name if cause is not None else None
        if cause is not None and missing != module:  # installed, but something under it is not
            text += f" ({cause})"
        super().__init__(text, name=module)
        self.extra = extra


def require(extra: str) -> None:
    """Import ``extra``'s module, or raise ``MissingExtra``: for a command to call before it
    does any work that ends in a figure or on a Zenoh bus."""
    try:
        importlib.import_module(EXTRAS[extra][0])
    except ImportError as exc:
        raise MissingExtra(extra, exc) from exc
