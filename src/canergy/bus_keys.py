"""Naming the nodes of a supervisor over several buses: ``can1/5`` is node 5 on the bus named
``can1``. The core keys that node's session ``bus index << 8 | node`` (bus 0: the plain node id);
names are for people and files, keys for the core. A supervisor on one bus (``-i/-c/--nodes``)
has no bus names and its nodes stay plain numbers everywhere.
"""

from __future__ import annotations

from collections.abc import Sequence

from canergy.core.supervisor import BUS_SHIFT
from canergy.messages import MAX_NODE, MIN_NODE

NODE_MASK = (1 << BUS_SHIFT) - 1


def session_key(bus: int, node: int) -> int:
    """The core's key of ``node`` on the bus at index ``bus``."""
    return bus << BUS_SHIFT | node


def bus_of(key: int) -> int:
    return key >> BUS_SHIFT


def node_of(key: int) -> int:
    return key & NODE_MASK


def node_name(buses: Sequence[str], key: int) -> int | str:
    """``key`` as status, replies and files show it: the node id without bus names, else
    ``bus/node``."""
    if not buses:
        return key
    return f"{buses[bus_of(key)]}/{node_of(key)}"


def parse_node_id(text: str) -> int | None:
    """A node id written in decimal without sign or leading zeros (``5``), else None."""
    if not (text.isascii() and text.isdigit() and str(int(text)) == text):
        return None
    node = int(text)
    return node if MIN_NODE <= node <= MAX_NODE else None


def parse_node_name(buses: Sequence[str], name: object) -> int:
    """The session key of a node as a user names it (``ValueError`` says what is wrong): a
    number without bus names or when there is one bus, ``bus/node`` with them."""
    if isinstance(name, int) and not isinstance(name, bool):
        if len(buses) > 1:
            raise ValueError(f"node {name}: name its bus too, one of {_choices(buses)}")
        if not MIN_NODE <= name <= MAX_NODE:
            raise ValueError(f"node {name}: ids are {MIN_NODE}-{MAX_NODE}")
        return name
    if not isinstance(name, str) or not buses:
        raise ValueError(f"node must be an integer {MIN_NODE}-{MAX_NODE}")
    bus, sep, text = name.rpartition("/")
    node = parse_node_id(text)
    if not sep or node is None:
        raise ValueError(f"node {name[:40]!r}: expected BUS/NODE, e.g. {buses[0]}/1")
    if bus not in buses:
        raise ValueError(f"node {name[:40]!r}: no bus named {bus[:40]!r} ({_choices(buses)})")
    return session_key(buses.index(bus), node)


def _choices(buses: Sequence[str]) -> str:
    return ", ".join(buses)
