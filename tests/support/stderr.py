"""What a run said on stderr, less the line every ``--no-fsync`` run starts with."""

from __future__ import annotations

from canergy.live.atomic import NO_FSYNC_WARNING


def without_no_fsync(err: str) -> str:
    """``err`` without the ``--no-fsync`` warning (``warn_no_fsync``), which tests pass for
    speed; the warning itself is tested in tests/test_no_fsync.py."""
    return "".join(line for line in err.splitlines(keepends=True) if NO_FSYNC_WARNING not in line)
