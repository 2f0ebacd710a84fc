"""The screen as lines of text, each with a style name; the curses loop only paints them.

Energies are integer µJ in the model and become joules here, at the edge.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from canergy.inspect.frames import Described
from canergy.inspect.others import tally
from canergy.inspect.render import line as frame_line
from canergy.messages import Telemetry
from canergy.monitor.model import Alarm, Row, Snapshot
from canergy.monitor.sessions import Ending, Phase
from canergy.monitor.view import KEYS_HELP, RAW_HELP, View

Line = tuple[str, str]
"""(text, style): style is ``title``, ``head``, ``normal``, ``selected``, ``alarm``, ``warn``,
``dim`` or ``prompt``."""

_BLOCKS = " ▏▎▍▌▋▊▉█"
_SPARKS = "▁▂▃▄▅▆▇█"
_ASCII_SPARKS = "_.-:=+*#"
SPARK_WIDTH = 40
"""Samples of the supervisor's usable budget in the sparkline (one per --books-period)."""


@dataclass(frozen=True, slots=True)
class Context:
    """What the screen says besides the snapshot."""

    source: str
    """The bus or capture, e.g. ``socketcan can0`` or ``replay cap.log``."""
    state: str
    """The feed's (``Feed.state``): ``live``, ``replay x1 3.2 s in``, ``replay done``..."""
    full_scale_uj: int | None = None
    """Level of a full bar; None: the highest level shown."""
    unicode: bool = True


def joules(uj: int) -> str:
    return f"{uj / 1e6:.3f} J"


def age(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    seconds = max(0.0, seconds)
    if seconds < 10:
        return f"{seconds:.1f}s"
    if seconds < 120:
        return f"{seconds:.0f}s"
    if seconds < 7200:
        return f"{seconds / 60:.0f}min"
    return f"{seconds / 3600:.0f}h"


def bar(fraction: float, width: int, unicode: bool) -> str:
    """A horizontal bar ``fraction`` full (clipped to 0..1), in eighths of a cell on UTF-8."""
    fraction = max(0.0, min(1.0, fraction))
    if not unicode:
        full = round(fraction * width)
        return "#" * full + "." * (width - full)
    eighths = round(fraction * width * 8)
    full, part = divmod(eighths, 8)
    text = "█" * full + (_BLOCKS[part] if part else "")
    return text + "░" * (width - len(text))


def sparkline(values: Sequence[int], width: int, unicode: bool) -> str:
    """The last ``width`` values as one character each, lowest to highest of those shown."""
    shown = list(values)[-width:]
    if not shown:
        return ""
    marks = _SPARKS if unicode else _ASCII_SPARKS
    low, high = min(shown), max(shown)
    if high == low:
        return marks[len(marks) // 2] * len(shown)
    top = len(marks) - 1
    return "".join(marks[round((v - low) * top / (high - low))] for v in shown)


def _rate(value: float) -> str:
    return f"{value:,.0f}"


def _kbits(bitrate: int) -> str:
    return f"{bitrate / 1000:g} kbit/s" if bitrate < 1_000_000 else f"{bitrate / 1e6:g} Mbit/s"


def header(snap: Snapshot, ctx: Context, width: int) -> list[Line]:
    title = f"canergy monitor  {ctx.source}"
    # The corner and the line below show one count, the snapshot's: every frame the model was
    # fed (canergy's, foreign, undecodable; MonitorModel.frames), at the moment the rest shows.
    count = f"{snap.frames:,} frames"
    stamp = f"{ctx.state}: {count}" if ctx.state else count
    lines: list[Line] = [(title + stamp.rjust(max(1, width - len(title))), "title")]
    load = (
        f"load {snap.load:.1%} of {_kbits(snap.bitrate)}"
        if snap.load is not None and snap.bitrate
        else "load n/a (give --bitrate)"
    )
    errors = sum(snap.errors.values())
    reasons = ", ".join(f"{k} {v}" for k, v in sorted(snap.errors.items(), key=lambda kv: -kv[1]))
    lines.append(
        (
            f"frames {snap.frames:,}  {_rate(snap.frames_per_s)} frames/s  {load}  "
            f"foreign {snap.foreign:,}{tally(snap.foreign_by)}  decode errors {errors:,}"
            + (f": {reasons}" if errors else ""),
            "warn" if errors else "normal",
        )
    )
    lines.append(_books_line(snap, ctx))
    return lines


def _books_line(snap: Snapshot, ctx: Context) -> Line:
    b = snap.books
    if b is None:
        return ("supervisor books: none (give --status-file or --control)", "dim")
    if b.nodes is None:
        return (f"supervisor books from {b.source}: {b.error}", "warn")
    shown = snap.usable_history[-SPARK_WIDTH:]
    values = [uj for _, uj in shown]
    spark = sparkline(values, SPARK_WIDTH, ctx.unicode)
    low, high = min(values), max(values)
    span = f" ({joules(low)} .. {joules(high)} in {age(snap.now - shown[0][0])})"
    text = (
        f"supervisor usable {joules(b.usable_uj)} {spark}{span}  "
        f"reserved {joules(b.reserved_uj)}  {b.variant}"
        + ("  LISTEN-ONLY" if b.listen_only else "")
        + ("  STOPPING" if b.stopping else "")
        + f"  books {age(snap.now - b.at + b.lag_s)} old"
    )
    if b.error is not None:
        return (f"{text}  (now: {b.error})", "warn")
    return (text, "normal")


def _level(row: Row, unicode: bool) -> str:
    """The node's level: reported (telemetry, or the books' copy of it), or ``≤`` the most the
    audit says it can hold; ``?`` when none is known."""
    if row.level_uj is None:
        return "?"
    bound = ("≤" if unicode else "<=") if row.level_source == "bound" else ""
    return bound + joules(row.level_uj)


def _state(row: Row) -> str:
    if row.joining:
        return "joining"
    if row.phase is not None:
        return "open"
    return "idle" if row.tx is not None else "-"


def _phase(row: Row) -> str:
    if row.phase is None:
        return "-"
    copies = f" x{row.sends}" if row.phase is Phase.INTENTION and row.sends > 1 else ""
    return f"{row.phase.value}{copies} {age(row.phase_age)}"


def _outcome(row: Row) -> str:
    o = row.last_outcome
    if o is None:
        return "-"
    amount = "" if o.ending is Ending.ABORTED else f" {joules(o.amount_uj)}"
    return f"{o.ending.value}{amount} {age(row.outcome_age)}"


def _flags(row: Row) -> str:
    flags = []
    if row.lost:
        flags.append("LOST")
    if row.alarms:
        flags.append(f"ALARM {row.alarms}")
    if row.flags & Telemetry.LOW:
        flags.append("LOW")
    if row.flags & Telemetry.HALTED:
        flags.append("HALTED")
    if row.damaged:
        flags.append(f"CRC {row.damaged}")
    return " ".join(flags)


def _books(row: Row) -> list[str]:
    """The supervisor's side: its session state and commits/aborts/write-offs."""
    b = row.books
    if b is None:
        return ["| -", ""]
    return [f"| {b.state}", f"{b.committed}/{b.aborted}/{b.written_off}"]


_BAR_MAX = 16
_FLAGS_ROOM = 12
"""Width kept for the flags (LOST ALARM 2...) before the bar gets any."""
_BAR_MIN = 4
_BOOKS = [("| books", 14, "<"), ("c/a/w", 10, "<")]


def _layout(label_width: int, width: int, books: bool) -> tuple[list[tuple[str, int, str]], int]:
    """(title, width, alignment) of each column, and the level bar's width: what is left of
    ``width`` (flags aside) up to 16 cells, none below 4."""
    columns = [
        ("node", label_width, ">"),
        ("level", 10, ">"),
        ("state", 7, "<"),
        ("tx", 6, ">"),
        ("phase", 17, "<"),
        ("commit", 6, ">"),
        ("abort", 5, ">"),
        ("w/o", 4, ">"),
        ("returns", 7, ">"),
        ("returned", 9, ">"),
        ("last outcome, age", 21, "<"),
        *(_BOOKS if books else []),
        ("flags", 0, "<"),
    ]
    used = sum(w + 1 for _, w, _ in columns) + _FLAGS_ROOM
    bar_width = min(_BAR_MAX, width - used - 1)
    if bar_width < _BAR_MIN:
        return columns, 0
    columns[1] = ("level", 10 + bar_width + 1, ">")
    return columns, bar_width


def _join(cells: Sequence[str], layout: Sequence[tuple[str, int, str]]) -> str:
    return " ".join(f"{c:{a}{w}}" for c, (_, w, a) in zip(cells, layout, strict=True)).rstrip()


def rows_lines(
    rows: Sequence[Row], view: View, ctx: Context, width: int, height: int, books: bool
) -> list[Line]:
    """The column titles and as many rows as fit in ``height``, scrolled to the selection."""
    label_width = max([4, *(len(r.label) for r in rows)])
    layout, bar_width = _layout(label_width, width, books)
    titles = [title for title, _, _ in layout]
    titles[1] = "level".ljust(layout[1][1])  # left, over the bar
    lines: list[Line] = [(_join(titles, layout), "head")]
    scale = ctx.full_scale_uj or max([1, *(r.level_uj or 0 for r in rows)])
    keys = [r.key for r in rows]
    at = keys.index(view.selected) if view.selected in keys else 0
    room = max(1, height)
    start = 0 if at < room else at - room + 1
    for r in rows[start : start + room]:
        level = f"{_level(r, ctx.unicode):>10}"
        if bar_width:
            level = bar((r.level_uj or 0) / scale, bar_width, ctx.unicode) + " " + level
        cells = [
            r.label,
            level,
            _state(r),
            str(r.tx) if r.tx is not None else "-",
            _phase(r),
            str(r.commits),
            str(r.aborts),
            str(r.write_offs),
            str(r.returns),
            joules(r.returned_uj),
            _outcome(r),
            *(_books(r) if books else []),
            _flags(r),
        ]
        style = "alarm" if r.alarms else "warn" if r.lost else "normal"
        lines.append((_join(cells, layout), "selected" if r.key == view.selected else style))
    if not rows:
        empty = "no canergy frames yet" if view.nodes is None else "no node in the filter"
        lines.append((f"  ({empty})", "dim"))
    return lines


Raw = tuple[list[Described], list[Alarm]]
"""The selected node's latest frames and its alarms (``MonitorModel.raw``)."""


def screen(
    snap: Snapshot, view: View, ctx: Context, width: int, height: int, raw: Raw | None = None
) -> list[Line]:
    """Every line of the screen, exactly ``height`` of them (the key help last), each cut to
    ``width``. ``raw``: the selected node's frames, for the raw view."""
    lines = header(snap, ctx, width)
    lines += [(f"! {note}", "warn") for note in snap.notes]
    rows = view.arrange(snap.rows)
    room = max(1, height - len(lines) - 2)
    if view.raw and view.selected is not None:
        lines += _raw_lines(view, rows, raw or ([], []), room + 1)
    else:
        lines.append(_status_line(snap, view, len(rows)))
        books = snap.books is not None and snap.books.nodes is not None
        lines += rows_lines(rows, view, ctx, width, room - 1, books)
    room = max(0, height - 1)
    lines = lines[:room]
    lines += [("", "normal")] * (room - len(lines))
    lines.append(_footer(view, ctx.unicode))
    return [(text[:width], style) for text, style in lines]


def _status_line(snap: Snapshot, view: View, shown: int) -> Line:
    total = len(snap.rows)
    nodes = f"{shown} of {total} nodes" if view.nodes is not None else f"{total} nodes"
    text = f"sort {view.sort}  filter {view.filter_text or 'all'}  {nodes}"
    if not snap.alarms:
        return (text, "normal")
    return (f"{text}  alarms {len(snap.alarms)}, latest {_alarm_text(snap.alarms[-1])}", "alarm")


def _alarm_text(a: Alarm) -> str:
    where = f"node {a.key[1]}: " if a.key is not None else ""
    return where + a.what


def _footer(view: View, unicode: bool) -> Line:
    if view.prompt is not None:
        now = view.filter_text or "all"
        return (
            f"filter nodes (now {now}; e.g. 3,5-7; empty: all; Esc cancels): {view.prompt}_",
            "prompt",
        )
    if view.message:
        return (view.message, "alarm")
    keys = RAW_HELP if view.raw else KEYS_HELP
    keys = keys if unicode else keys.replace("↑↓", "arrows")
    return (keys + ("  n step" if view.paused else ""), "dim")


def _raw_lines(view: View, rows: list[Row], raw: Raw, height: int) -> list[Line]:
    frames, alarms = raw
    row = next(r for r in rows if r.key == view.selected)
    where = f" on {row.key[0]}" if row.key[0] else ""
    alarm_lines = [(f"!! {a.what}", "alarm") for a in alarms[-5:]]
    room = max(1, height - 1 - len(alarm_lines))
    shown = frames[-room:]
    lines: list[Line] = [
        (
            f"raw frames of node {row.label}{where}: the latest {len(shown)} of {row.frames:,}",
            "head",
        )
    ]
    lines += [(frame_line(d, colour=False), "normal") for d in shown]
    return lines + alarm_lines
