"""Errors raised by the core for requests its caller should not have made."""


class LocalProtocolError(ValueError):
    """The local application asked for something the protocol does not allow now."""
