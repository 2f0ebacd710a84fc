"""``evolve``: a faster ``dataclasses.replace`` for the core's frozen, slotted state records.

The model checker builds millions of states; ``dataclasses.replace`` re-inspects the fields on
every call. Here each class gets, on first use, a generated copier whose keyword parameters are
the field names (so Python itself rejects unknown names) and which copies every slot directly
(no ``__post_init__`` runs: state records have none).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")
_MISSING: Any = object()
_COPIERS: dict[type, Callable[..., Any]] = {}


def _copier(cls: type) -> Callable[..., Any]:
    names: tuple[str, ...] = cls.__slots__  # type: ignore[attr-defined]
    params = ", ".join(f"{n}=_MISSING" for n in names)
    body = "".join(f"    _set(new, {n!r}, obj.{n} if {n} is _MISSING else {n})\n" for n in names)
    source = f"def copy(obj, *, {params}):\n    new = _new(cls)\n{body}    return new\n"
    scope: dict[str, Any] = {
        "_MISSING": _MISSING,
        "_set": object.__setattr__,
        "_new": object.__new__,
        "cls": cls,
    }
    exec(source, scope)  # source built only from the class's own slot names
    copy: Callable[..., Any] = scope["copy"]
    return copy


def evolve(obj: T, **changes: Any) -> T:
    """A copy of ``obj`` with ``changes`` applied; unknown field names raise ``TypeError``."""
    cls = type(obj)
    copy = _COPIERS.get(cls)
    if copy is None:
        copy = _COPIERS[cls] = _copier(cls)
    try:
        new: T = copy(obj, **changes)
    except TypeError as exc:
        unknown = sorted(set(changes) - set(cls.__slots__))  # type: ignore[attr-defined]
        raise TypeError(f"{cls.__name__} has no field(s) {unknown}") from exc
    return new
