"""Errors the command line reports in one line, importable without python-can."""


class BusOpenError(RuntimeError):
    """The bus could not be opened; the message says what to fix."""
