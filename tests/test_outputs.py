"""The supervisor's outputs, each its own part: the books and the status."""

from __future__ import annotations

import io
import json
from pathlib import Path

from canergy.core import Supervisor
from canergy.live.supervisor.outputs import BooksOut, StatusOut
from canergy.live.supervisor.state_file import load_state

J = 1_000_000


class _Gone(io.StringIO):
    def write(self, text: str) -> int:
        raise BrokenPipeError


def test_a_status_stream_whose_reader_went_away_is_dropped_and_the_file_kept(
    tmp_path: Path,
) -> None:
    path = tmp_path / "status.json"
    out = StatusOut(path, _Gone())
    out.write({"n": 1})
    assert out.stream is None
    out.write({"n": 2})  # no second attempt on the stream, the file still written
    assert json.loads(path.read_text()) == {"n": 2}


def test_a_status_line_is_made_by_text_when_given() -> None:
    stream = io.StringIO()
    StatusOut(None, stream, text=lambda s: f"n={s['n']}").write({"n": 3})
    StatusOut(None, stream).write({"n": 4})
    assert stream.getvalue().splitlines() == ["n=3", '{"n": 4}']


def test_the_books_go_to_the_callers_save_before_the_file(tmp_path: Path) -> None:
    core = Supervisor((1,), 2 * J)
    saved: list[int] = []
    through = BooksOut(core, tmp_path / "a.json", fsync=False, save=lambda: saved.append(1))
    through.write()
    assert (saved, through.saves, (tmp_path / "a.json").exists()) == ([1], 1, False)
    to_file = BooksOut(core, tmp_path / "b.json", fsync=False)
    to_file.write()
    assert load_state(tmp_path / "b.json", "hardened", (1,)).usable == 2 * J
    nowhere = BooksOut(core, None)
    nowhere.write()
    assert nowhere.saves == 0  # nothing written, nothing counted
