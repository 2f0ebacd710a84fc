"""Fast building and copying of frozen, slotted records (the protocol's messages, states,
inputs and actions), which the live loop makes several of per frame and the model checker
millions of.

A frozen dataclass's own ``__init__`` (and ``dataclasses.replace``) sets each field through
``object.__setattr__``, a lookup by name per field. Here each class gets generated code that
sets every slot through the slot's own descriptor: ``fast_init`` replaces the ``__init__`` of a
record (same parameters, same defaults), ``evolve`` copies one with changes.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")
_MISSING: Any = object()
_COPIERS: dict[type, Callable[..., Any]] = {}


def _slots(cls: type) -> dict[str, Any]:
    """Every slot of ``cls`` and of its bases, base first, with its member descriptor."""
    found: dict[str, Any] = {}
    for klass in reversed(cls.__mro__):
        slots = getattr(klass, "__slots__", ())
        for name in (slots,) if isinstance(slots, str) else slots:
            found[name] = klass.__dict__[name]
    return found


def _generate(cls: type, head: str, values: dict[str, str], scope: dict[str, Any]) -> Any:
    """Compile ``head`` (``init(__record, ...)`` fills ``__record``; ``copy(__source, ...)``
    makes and returns it) with one descriptor call per slot; ``values``: each slot's value as an
    expression. The generated code's own names start with ``__``, so no field name meets them."""
    make = head.startswith("copy")
    body = "".join(f"    __set_{i}(__record, {values[n]})\n" for i, n in enumerate(values))
    source = f"def {head}:\n" + ("    __record = __new(__cls)\n" if make else "") + body
    source += "    return __record\n" if make else "    return None\n"
    slots = _slots(cls)
    scope |= {f"__set_{i}": slots[n].__set__ for i, n in enumerate(values)}
    scope |= {"__cls": cls, "__new": object.__new__}
    exec(source, scope)  # built only from the class's field names
    return scope[head.partition("(")[0]]


def fast_init(cls: type[T]) -> type[T]:
    """Give a frozen, slotted dataclass an ``__init__`` with the same parameters and defaults
    that sets its slots through their descriptors. Only for plain records: no ``__post_init__``,
    no default factory, no keyword-only field, every field in ``__init__`` and in a slot."""
    fields = dataclasses.fields(cls)  # type: ignore[arg-type]
    names = tuple(f.name for f in fields)
    plain = all(
        f.init and not f.kw_only and f.default_factory is dataclasses.MISSING for f in fields
    )
    if not plain or hasattr(cls, "__post_init__") or tuple(_slots(cls)) != names:
        raise TypeError(f"{cls.__name__}: fast_init takes plain frozen, slotted records only")
    params = "".join(
        f", {f.name}" if f.default is dataclasses.MISSING else f", {f.name}=__default_{i}"
        for i, f in enumerate(fields)
    )
    defaults = {f"__default_{i}": f.default for i, f in enumerate(fields)}
    init = _generate(cls, f"init(__record{params})", {n: n for n in names}, defaults)
    init.__qualname__ = f"{cls.__qualname__}.__init__"
    cls.__init__ = init  # type: ignore[method-assign]
    return cls


def _new_copier(cls: type) -> Callable[..., Any]:
    """Generate ``cls``'s copier (every slot a keyword, the source's value when not given) and
    keep it for the next ``evolve``."""
    names = tuple(_slots(cls))
    params = "".join(f", {n}=__missing" for n in names)
    values = {n: f"__source.{n} if {n} is __missing else {n}" for n in names}
    copy: Callable[..., Any] = _generate(
        cls,
        f"copy(__source, *{params})" if names else "copy(__source)",
        values,
        {"__missing": _MISSING},
    )
    _COPIERS[cls] = copy
    return copy


def evolve(obj: T, **changes: Any) -> T:
    """A copy of ``obj`` with ``changes`` applied; unknown field names raise ``TypeError``."""
    cls = type(obj)
    try:
        new: T = (_COPIERS.get(cls) or _new_copier(cls))(obj, **changes)
    except TypeError as exc:
        unknown = sorted(set(changes) - set(_slots(cls)))
        raise TypeError(f"{cls.__name__} has no field(s) {unknown}") from exc
    return new
