"""Errors raised by the core for requests its caller should not have made."""


class LocalProtocolError(ValueError):
    """The local application asked for something the protocol does not allow now."""


class WindowClosed(LocalProtocolError):
    """Witnessed rules: a begin refused because the node's window is used up (k > W + B); a
    re-sync of the node (``Supervisor.resync``) opens it again."""
