"""The curses loop: read keys, take a snapshot a few times a second, paint the rendered lines.

curses (the standard library) rather than a widget toolkit: no dependency to install on a robot's
host, it works over ssh, a serial console and tmux, and it sends only the cells that changed.
"""

from __future__ import annotations

import contextlib
import curses
import os
import signal
import threading
import time
from dataclasses import replace

from canergy.monitor.feeds import Feed
from canergy.monitor.model import MonitorModel, Snapshot
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
    snap: Snapshot | None = None
    raw: Raw | None = None
    drawn = 0.0
    shown: list[tuple[str, int]] = []
    while not view.quit:
        key = _key(stdscr)
        changed = key is not None
        while key is not None and not view.quit:
            if key == "KEY_RESIZE":
                curses.update_lines_cols()
            else:
                view.handle(key, shown)
                raw = None  # the raw view may show another node now
            key = _key_now(stdscr)
        feed.pause(view.paused)
        stepped = view.steps > 0
        while view.steps:
            feed.step()
            view.steps -= 1
        due = time.monotonic() - drawn >= refresh_s
        if snap is None or stepped or (due and not view.paused):
            now = feed.now()
            with lock:
                snap = model.snapshot(now)
                if view.raw and view.selected is not None:
                    raw = model.raw(view.selected)
            drawn = time.monotonic()
            changed = True
        elif view.raw and raw is None and view.selected is not None:
            with lock:
                raw = model.raw(view.selected)
        if not view.raw:
            raw = None
        if changed:
            height, width = stdscr.getmaxyx()
            state = feed.state(view.paused)
            lines = screen(snap, view, replace(ctx, state=state), width, height, raw)
            shown = [r.key for r in view.arrange(snap.rows)]
            _paint(stdscr, lines, styles)


def _key_now(stdscr: curses.window) -> str | None:
    """Another key already typed, without waiting."""
    stdscr.nodelay(True)
    try:
        return _key(stdscr)
    finally:
        stdscr.timeout(KEY_WAIT_MS)
