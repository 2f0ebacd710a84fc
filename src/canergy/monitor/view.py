"""What the user chose on the screen (filter, sort, selection, pause, raw view) and the keys.

Keys arrive as text: a character, or a curses key name such as ``KEY_UP``; nothing here needs a
terminal, so the tests drive it directly.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass

from canergy.argtypes import node_ids
from canergy.monitor.model import Key, Row

SORTS = ("node", "level", "activity", "trouble")
"""node: by channel and id; level: fullest first; activity: latest frame first; trouble: alarms,
lost nodes and write-offs first."""

ENTER = frozenset({"\n", "\r", "KEY_ENTER"})
BACK = frozenset({"\x1b", "KEY_LEFT", "KEY_BACKSPACE", "\x7f", "\b"})
ERASE = frozenset({"KEY_BACKSPACE", "\x7f", "\b"})
KEYS_HELP = "q quit  p pause  / filter  s sort  ↑↓ select  Enter raw frames"
RAW_HELP = "Esc/Enter back  ↑↓ other node  q quit  p pause"


EVERY_NODE = frozenset({"", "all", "*"})
"""Filters that show every node (what ``parse_filter`` returns None for)."""


def parse_filter(text: str) -> frozenset[int] | None:
    """``3,5-7`` as node ids; empty, ``all`` or ``*``: every node (None). ``ValueError`` says
    what is wrong."""
    if text.strip().lower() in EVERY_NODE:
        return None
    try:
        return frozenset(node_ids(text))
    except argparse.ArgumentTypeError as exc:
        raise ValueError(str(exc)) from None


def _sort_key(sort: str, row: Row) -> tuple[object, ...]:
    if sort == "level":
        return (row.level_uj is None, -(row.level_uj or 0), row.key)
    if sort == "activity":
        age = row.last_frame_age
        return (age is None, age or 0.0, row.key)
    if sort == "trouble":
        return (-row.alarms, not row.lost, -row.write_offs, -row.damaged, row.key)
    return (row.key,)


@dataclass(slots=True)
class View:
    sort: str = "node"
    nodes: frozenset[int] | None = None
    filter_text: str = ""
    paused: bool = False
    selected: Key | None = None
    raw: bool = False
    prompt: str | None = None
    """The filter being typed, or None. It opens empty, so ``/`` then Enter shows every node
    again; the filter in force stays on the status line until Enter replaces it."""
    message: str = ""
    quit: bool = False
    steps: int = 0
    """Single steps of a paused replay asked for and not yet taken."""

    def arrange(self, rows: Sequence[Row]) -> list[Row]:
        """The rows shown: filtered, sorted; the selection moved onto one of them."""
        shown = [r for r in rows if self.nodes is None or r.node in self.nodes]
        shown.sort(key=lambda r: _sort_key(self.sort, r))
        keys = [r.key for r in shown]
        if self.selected not in keys:
            self.selected = keys[0] if keys else None
            if self.raw and self.selected is None:
                self.raw = False
        return shown

    def handle(self, key: str, shown: Sequence[Key]) -> None:
        """One key press; ``shown``: the keys of the rows on screen, in order."""
        self.message = ""
        if self.prompt is not None:
            self._prompt_key(key)
        elif key in ("q", "Q"):
            self.quit = True
        elif key in ("p", "P", " "):
            self.paused = not self.paused
        elif key == "n" and self.paused:
            self.steps += 1
        elif self.raw:
            if key in BACK or key in ENTER or key == "r":
                self.raw = False
            else:  # the previous or next node's frames
                self._move(key, list(shown))
        elif key in ("/", "f"):
            self.prompt = ""
        elif key == "s":
            self.sort = SORTS[(SORTS.index(self.sort) + 1) % len(SORTS)]
        elif key in ENTER or key == "r":
            self.raw = self.selected is not None
        else:
            self._move(key, list(shown))

    def _move(self, key: str, shown: list[Key]) -> None:
        if not shown:
            return
        at = shown.index(self.selected) if self.selected in shown else 0
        step = {"KEY_UP": -1, "k": -1, "KEY_DOWN": 1, "j": 1, "KEY_PPAGE": -10, "KEY_NPAGE": 10}
        if key in step:
            at += step[key]
        elif key == "KEY_HOME":
            at = 0
        elif key == "KEY_END":
            at = len(shown) - 1
        else:
            return
        self.selected = shown[max(0, min(len(shown) - 1, at))]

    def _prompt_key(self, key: str) -> None:
        assert self.prompt is not None
        if key in ENTER:
            try:
                self.nodes = parse_filter(self.prompt)
            except ValueError as exc:
                self.message = f"filter: {exc}"
                return
            self.filter_text = self.prompt.strip() if self.nodes is not None else ""
            self.prompt = None
        elif key == "\x1b":
            self.prompt = None
        elif key in ERASE:
            self.prompt = self.prompt[:-1]
        elif len(key) == 1 and key.isprintable() and len(self.prompt) < 200:
            self.prompt += key
