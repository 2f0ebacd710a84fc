"""``fast_init`` and ``evolve`` build the same records as the dataclasses they speed up."""

from __future__ import annotations

import dataclasses
import inspect
from dataclasses import dataclass, field

import pytest

from canergy import messages
from canergy.core import actions, inputs, state
from canergy.core.state import Session
from canergy.frozen import evolve, fast_init


@dataclass(frozen=True, slots=True)
class Plain:
    a: int
    b: str = "b"
    c: tuple[int, ...] = ()


@fast_init
@dataclass(frozen=True, slots=True)
class Fast:  # the same fields as Plain
    a: int
    b: str = "b"
    c: tuple[int, ...] = ()


@pytest.mark.parametrize(
    ("args", "kwargs"),
    [((1,), {}), ((1, "x"), {}), ((1,), {"c": (2,)}), ((), {"a": 3, "b": "y", "c": (4, 5)})],
)
def test_fast_init_sets_what_the_dataclass_init_sets(args: tuple, kwargs: dict) -> None:
    slow, fast = Plain(*args, **kwargs), Fast(*args, **kwargs)
    assert dataclasses.astuple(slow) == dataclasses.astuple(fast)
    assert repr(fast) == repr(slow).replace("Plain", "Fast")
    with pytest.raises(dataclasses.FrozenInstanceError):
        fast.a = 2  # type: ignore[misc]


@pytest.mark.parametrize(
    ("args", "kwargs"), [((), {}), ((1, "x", (), 4), {}), ((1,), {"d": 1}), ((1,), {"a": 2})]
)
def test_fast_init_refuses_what_the_dataclass_init_refuses(args: tuple, kwargs: dict) -> None:
    with pytest.raises(TypeError):
        Plain(*args, **kwargs)
    with pytest.raises(TypeError):
        Fast(*args, **kwargs)


RECORD_MODULES = (messages, actions, inputs, state)


def test_the_protocol_records_keep_their_signatures() -> None:
    records = [
        cls
        for module in RECORD_MODULES
        for cls in vars(module).values()
        if isinstance(cls, type) and cls.__module__ == module.__name__
        if dataclasses.is_dataclass(cls)
    ]
    assert len(records) >= 30  # messages, actions, inputs and states
    for cls in records:
        params = list(inspect.signature(cls).parameters.values())
        fields = dataclasses.fields(cls)
        assert [p.name for p in params] == [f.name for f in fields], cls
        assert all(p.kind is inspect.Parameter.POSITIONAL_OR_KEYWORD for p in params), cls
        assert [p.default for p in params] == [
            inspect.Parameter.empty if f.default is dataclasses.MISSING else f.default
            for f in fields
        ], cls


def test_names_the_generated_code_uses_are_free_for_fields() -> None:
    @dataclass(frozen=True, slots=True)
    class Base:
        new: int

    @fast_init
    @dataclass(frozen=True, slots=True)
    class Derived(Base):  # fields of a base class, and names a generator might use itself
        cls: int = 1
        obj: int = 2

    record = Derived(0, obj=5)
    assert (record.new, record.cls, record.obj) == (0, 1, 5)
    assert evolve(record, new=3, cls=4) == Derived(3, 4, 5)


def test_fast_init_takes_plain_records_only() -> None:
    @dataclass(frozen=True, slots=True)
    class Derived:
        a: int

        def __post_init__(self) -> None:
            pass

    @dataclass(frozen=True, slots=True)
    class Factory:
        a: list[int] = field(default_factory=list)

    @dataclass(frozen=True)
    class NoSlots:
        a: int

    @dataclass(frozen=True, slots=True)
    class KeywordOnly:
        a: int = field(kw_only=True)
        b: int = 0

    for cls in (Derived, Factory, NoSlots, KeywordOnly):
        with pytest.raises(TypeError, match="plain frozen, slotted records only"):
            fast_init(cls)


def test_evolve_changes_only_what_it_is_told() -> None:
    s = Session(5, tx=3, reserved=1000)
    t = evolve(s, tx=4, deadline=9)
    assert t == dataclasses.replace(s, tx=4, deadline=9) and s.tx == 3
    with pytest.raises(TypeError, match=r"Session has no field\(s\) \['txx'\]"):
        evolve(s, txx=4)
