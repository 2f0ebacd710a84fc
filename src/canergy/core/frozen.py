"""``evolve``: a faster ``dataclasses.replace`` for the core's frozen, slotted state records.

The model checker builds millions of states; ``dataclasses.replace`` re-inspects the fields on
every call, this copies the slots directly (no ``__post_init__`` runs: state records have none).
"""

from __future__ import annotations

from typing import Any, TypeVar

T = TypeVar("T")
_set = object.__setattr__
_FIELDS: dict[type, tuple[tuple[str, ...], frozenset[str]]] = {}


def evolve(obj: T, **changes: Any) -> T:
    """A copy of ``obj`` with ``changes`` applied; unknown field names raise ``TypeError``."""
    cls = type(obj)
    fields = _FIELDS.get(cls)
    if fields is None:
        names: tuple[str, ...] = cls.__slots__  # type: ignore[attr-defined]
        fields = _FIELDS[cls] = (names, frozenset(names))
    if not fields[1].issuperset(changes):
        raise TypeError(f"{cls.__name__} has no field(s) {sorted(set(changes) - fields[1])}")
    new = object.__new__(cls)
    for name in fields[0]:
        _set(new, name, changes[name] if name in changes else getattr(obj, name))
    return new
