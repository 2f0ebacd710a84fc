"""What the supervisor writes out, one job each: its books (``BooksOut``: the state file, or a
save of the caller's) and its status (``StatusOut``: a JSON file, and/or one JSON object or one
line a status on a stream). The service decides when; these only write."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

from canergy.core.supervisor import SupervisorCore
from canergy.live.atomic import write_json_atomic
from canergy.live.supervisor.state_file import BooksWriter


class BooksOut:
    """Writes ``core``'s persistent record: through ``save`` when given (a gateway keeps both of
    its roles in one file), else to ``path`` (None, with no ``save``: kept nowhere)."""

    def __init__(
        self,
        core: SupervisorCore,
        path: Path | None,
        *,
        fsync: bool = True,
        buses: tuple[str, ...] = (),
        save: Callable[[], None] | None = None,
    ) -> None:
        self.core = core
        self.save = save
        self.writer = (
            None
            if path is None or save is not None
            else BooksWriter(path, core.variant.name, fsync=fsync, buses=buses)
        )
        self.saves = 0
        """Times the books were written."""

    def write(self) -> None:
        if self.save is not None:
            self.save()
        elif self.writer is not None:
            self.writer.save(self.core.state)
        else:
            return
        self.saves += 1


class StatusOut:
    """Writes a status to ``path`` (JSON, atomically) and to ``stream``: one JSON object a line,
    or the line ``text`` makes of it. A stream whose reader went away (``| head``) is dropped:
    supervising goes on."""

    def __init__(
        self,
        path: Path | None,
        stream: TextIO | None,
        text: Callable[[dict[str, Any]], str] | None = None,
    ) -> None:
        self.path = path
        self.stream = stream
        self.text = text

    def write(self, status: dict[str, Any]) -> None:
        if self.path is not None:
            write_json_atomic(self.path, status, fsync=False)
        if self.stream is not None:
            line = json.dumps(status, sort_keys=True) if self.text is None else self.text(status)
            try:
                self.stream.write(line + "\n")
                self.stream.flush()
            except BrokenPipeError:
                self.stream = None
