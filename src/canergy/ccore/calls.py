"""The signatures of the compiled core's frame-path calls, for those who hold them (the service,
``CompiledBuses``) without loading the C extension."""

from __future__ import annotations

from collections.abc import Callable

from canergy.core.actions import Action
from canergy.messages import Message

Answer = Callable[
    [int, bytes | bytearray, bool, bool, int, bool],
    tuple[int, list[Action], list[tuple[int, bytes]], Message | None, int],
]
"""``CompiledSupervisor.on_answer``: one bus's frame path into the C core."""
AuthAnswer = Callable[
    [int, bytes | bytearray, bool, bool, int, bool],
    tuple[int, list[Action], list[tuple[int, bytes]], int],
]
"""``CompiledSupervisor.on_auth_answer``: one bus's frame path with a key (FD layout)."""
AuthPair = Callable[
    [int, bytes, int, bytes | bytearray, bool, bool, int, bool],
    tuple[int, list[Action], list[tuple[int, bytes]], int],
]
"""``CompiledSupervisor.on_auth_pair``: one bus's frame path with a key (classic layout)."""
EncodedBegin = Callable[[int, int, int], tuple[list[Action], list[tuple[int, bytes]]]]
"""``CompiledSupervisor.begin_encoded``: actions, and the INTENTION as C encoded it."""
