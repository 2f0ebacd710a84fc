"""The demo's frame capture (``--log``), opened before any bus.

Bad paths are reported naming ``--log``; a run that fails before capturing a frame leaves no file.
"""

from __future__ import annotations

from pathlib import Path
from types import TracebackType

import can

CHANNEL = "virtual0"
"""Channel name written with every captured frame."""


def check_log_path(path: Path) -> None:
    """Raise ``ValueError`` naming ``--log`` unless ``path`` is a file name in a directory."""
    parent = path.parent
    if not parent.is_dir():
        problem = "is not a directory" if parent.exists() else "does not exist"
        raise ValueError(f"--log {path}: {parent} {problem}")
    if path.is_dir():
        raise ValueError(f"--log {path}: is a directory")


class Capture:
    """Writes frames to ``path`` in the format its suffix names (python-can's writers)."""

    def __init__(self, path: Path) -> None:
        check_log_path(path)
        try:
            self._writer = can.Logger(str(path))
        except (OSError, ValueError) as exc:
            raise ValueError(f"--log {path}: {exc}") from exc
        self.path = path
        self.frames = 0

    def write(self, frame: can.Message) -> None:
        frame.channel = CHANNEL
        self._writer.on_message_received(frame)
        self.frames += 1

    def __enter__(self) -> Capture:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._writer.stop()
        if exc_type is not None and self.frames == 0:
            self.path.unlink(missing_ok=True)
