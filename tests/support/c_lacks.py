"""What the C port does not implement yet, which the side-by-side tests expect it to refuse."""

from __future__ import annotations

from canergy.messages import MsgType

C_LACKS = frozenset({MsgType.DEBIT})
"""The witnessed rule set's frame (``canergy.core.witnessed``): the C codec refuses it as an
unknown type, and its data length there is 0."""


def c_lacks(base: int, arbitration_id: int, extended: bool = True) -> bool:
    """An identifier in the block of a type C_LACKS (where Python refuses the frame for
    another reason, a bad node or the wrong direction included, C refuses the type first)."""
    if not extended or arbitration_id & 0x1FFFF000 != base:
        return False
    return arbitration_id >> 8 & 0xF in {int(t) for t in C_LACKS}
