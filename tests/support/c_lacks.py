"""What the C port does not implement yet, which the side-by-side tests expect it to refuse."""

from __future__ import annotations

from canergy.messages import MsgType

C_LACKS = frozenset({MsgType.DEBIT})
"""The witnessed rule set's frame (``canergy.core.witnessed``): the C codec refuses it as an
unknown type, and its data length there is 0."""
