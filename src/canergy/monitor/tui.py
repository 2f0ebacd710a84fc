"""The curses loop: read keys, take a snapshot a few times a second, paint the rendered lines.

curses (the standard library) rather than a widget toolkit: no dependency to install on a robot's
host, it works over ssh, a serial console and tmux, and it sends only the cells that changed.
"""

from __future__ import annotations

import contextlib
import curses
import math
import os
import signal
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import replace

from canergy.monitor.feeds import Feed
from canergy.monitor.model import Key, MonitorModel, Snapshot
from canergy.monitor.render import Context, Line, Raw, screen
from canergy.monitor.view import View

KEY_WAIT_MS = 50


def run(
    feed: Feed,
    model: MonitorModel,
    lock: threading.Lock,
    view: View,
    ctx: Context,
    refresh_s: float,
) -> None:
    """Until the user quits (q, Ctrl-C or SIGTERM); the terminal is restored on every path."""
    main = threading.current_thread() is threading.main_thread()
    previous = {}
    if main:
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, lambda *_: setattr(view, "quit", True))
    for stale in ("LINES", "COLUMNS"):  # curses would take them over the terminal's own size
        os.environ.pop(stale, None)
    try:
        curses.wrapper(_loop, feed, model, lock, view, ctx, refresh_s)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _styles() -> dict[str, int]:
    styles = {
        "title": curses.A_REVERSE | curses.A_BOLD,
        "head": curses.A_BOLD,
        "normal": curses.A_NORMAL,
        "selected": curses.A_REVERSE,
        "alarm": curses.A_BOLD,
        "warn": curses.A_NORMAL,
        "dim": curses.A_DIM,
        "prompt": curses.A_BOLD,
    }
    if curses.has_colors():
        curses.start_color()
        try:
            curses.use_default_colors()
            background = -1
        except curses.error:
            background = curses.COLOR_BLACK
        curses.init_pair(1, curses.COLOR_RED, background)
        curses.init_pair(2, curses.COLOR_YELLOW, background)
        styles["alarm"] = curses.color_pair(1) | curses.A_BOLD
        styles["warn"] = curses.color_pair(2)
    return styles


def _key(stdscr: curses.window) -> str | None:
    try:
        key = stdscr.get_wch()
    except curses.error:
        return None
    if isinstance(key, int):
        return curses.keyname(key).decode(errors="replace")
    return key


def _paint(stdscr: curses.window, lines: list[Line], styles: dict[str, int]) -> None:
    height, width = stdscr.getmaxyx()
    stdscr.erase()
    for y, (text, style) in enumerate(lines[:height]):
        cut = width - 1 if y == height - 1 else width  # the last cell scrolls the screen
        with contextlib.suppress(curses.error):  # a line wider than a shrinking window
            stdscr.addnstr(y, 0, text, cut, styles.get(style, curses.A_NORMAL))
    stdscr.noutrefresh()
    curses.doupdate()


class Display:
    """What the loop paints and when, without curses (the tests drive it with keys and a clock).

    A snapshot is taken every ``refresh_s`` unless paused, on a step, and when the pause is
    toggled: pausing freezes the screen at that moment. The feed's state is read with each
    snapshot, so no part of the screen is newer than the rest. The screen is painted after every
    key (a resize included), with each snapshot, and every ``refresh_s`` while paused too: the
    frozen snapshot, in the view and the window size of now.
    """

    def __init__(
        self,
        feed: Feed,
        model: MonitorModel,
        lock: threading.Lock,
        view: View,
        ctx: Context,
        refresh_s: float,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.feed, self.model, self.lock, self.view = feed, model, lock, view
        self.ctx, self.refresh_s, self.clock = ctx, refresh_s, clock
        self.snap: Snapshot | None = None
        self.raw: Raw | None = None
        self.ticked = -math.inf
        """Clock of the latest periodic paint."""
        self.shown: list[Key] = []
        """The keys of the rows painted, in order (for the arrow keys)."""

    def update(self, keys: Sequence[str], width: int, height: int) -> list[Line] | None:
        """Take the keys typed since the last call (``KEY_RESIZE`` once the window changed size)
        and return the screen to paint, or None when nothing is due."""
        view = self.view
        was_paused = view.paused
        for key in keys:
            if view.quit:
                break
            if key != "KEY_RESIZE":
                view.handle(key, self.shown)
                self.raw = None  # the raw view may show another node now
        self.feed.pause(view.paused)
        stepped = view.steps > 0
        while view.steps:
            self.feed.step()
            view.steps -= 1
        now = self.clock()
        due = now - self.ticked >= self.refresh_s
        if due:
            self.ticked = now
        fresh = (
            self.snap is None or stepped or view.paused != was_paused or (due and not view.paused)
        )
        if fresh:
            self._take()
        elif view.raw and self.raw is None and view.selected is not None and self.snap is not None:
            with self.lock:
                self.raw = self.model.raw(view.selected, self.snap)
        if not view.raw:
            self.raw = None
        if not (keys or fresh or due) or self.snap is None:
            return None
        snap, ctx = self.snap, self.ctx
        lines = screen(snap, view, ctx, width, height, self.raw)
        self.shown = [r.key for r in view.arrange(snap.rows)]
        return lines

    def _take(self) -> None:
        """A snapshot, with the feed's state of the same moment (read first: a replay said to be
        done has fed its every frame to the model before the snapshot)."""
        view = self.view
        state = self.feed.state(view.paused)
        now = self.feed.now()
        with self.lock:
            self.snap = snap = self.model.snapshot(now)
            if view.raw and view.selected is not None:
                self.raw = self.model.raw(view.selected, snap)
        self.ctx = replace(self.ctx, state=state)


def _loop(
    stdscr: curses.window,
    feed: Feed,
    model: MonitorModel,
    lock: threading.Lock,
    view: View,
    ctx: Context,
    refresh_s: float,
) -> None:
    with contextlib.suppress(curses.error):  # a terminal without cursor control
        curses.curs_set(0)
    curses.set_escdelay(25)  # Esc alone leaves the raw view at once, not after a second
    stdscr.timeout(KEY_WAIT_MS)
    styles = _styles()
    display = Display(feed, model, lock, view, ctx, refresh_s)
    while not view.quit:
        keys: list[str] = []
        key = _key(stdscr)
        while key is not None:
            if key == "KEY_RESIZE":
                curses.update_lines_cols()
                stdscr.clearok(True)  # all of it again: a terminal may reflow what it showed
            keys.append(key)
            key = _key_now(stdscr)
        height, width = stdscr.getmaxyx()
        lines = display.update(keys, width, height)
        if lines is not None:
            _paint(stdscr, lines, styles)


def _key_now(stdscr: curses.window) -> str | None:
    """Another key already typed, without waiting."""
    stdscr.nodelay(True)
    try:
        return _key(stdscr)
    finally:
        stdscr.timeout(KEY_WAIT_MS)
