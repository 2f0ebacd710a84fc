"""What the monitor knows, fed frame by frame: curses-free, clock-free, one lock held by callers.

``feed(frame, t)`` takes every frame with the time it was seen (the monitor's clock: monotonic
on a bus, the capture's timestamps in a replay) and ``snapshot(now)`` returns an immutable view
for the renderer. Per node: a ``NodeTrack`` (phases, outcomes, telemetry, latest frames) and the
audit's books (``canergy.inspect.audit``), which raise the alarms and bound what a node holds.
The audit keeps every transaction it saw, so on a bus it is restarted every ``audit_segment``
frames, as if a new capture began: memory stays bounded and alarms already raised are kept.
"""

from __future__ import annotations

import gc
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, replace

import can

from canergy.auth.capture import CaptureAuth
from canergy.codec import Codec, DecodeErrorReason
from canergy.inspect.audit import Auditor
from canergy.inspect.frames import Described, describe
from canergy.inspect.others import Namer, protocol_of
from canergy.monitor.books import BookNode, Books
from canergy.monitor.busload import frame_seconds
from canergy.monitor.sessions import NodeTrack, Outcome, Phase

Key = tuple[str, int]
"""(channel, node): node 5 on two buses is two nodes."""

FREEZE_EVERY = 20_000
"""Frames after which everything alive is moved out of the cyclic garbage collector's sight
(``gc.freeze``): the audit's books are long-lived and free of cycles (reference counting still
frees them), and a full collection over them stalled the reader for 150 ms at 150,000 frames,
longer than SocketCAN's default receive buffer lasts at 5,000 frames/s; now a few ms."""
AUDIT_SEGMENT = 200_000
"""Frames after which the audit starts afresh (about 100 MB of its books at most)."""
USABLE_HISTORY = 240
"""Samples of the supervisor's usable budget kept for the sparkline."""
ALARMS_KEPT = 200

ERROR_LABELS = {
    DecodeErrorReason.BAD_CRC.value: "crc",
    DecodeErrorReason.WRONG_DLC.value: "dlc",
    DecodeErrorReason.UNKNOWN_TYPE.value: "type",
    DecodeErrorReason.BAD_NODE.value: "node",
    DecodeErrorReason.REMOTE_FRAME.value: "remote",
    DecodeErrorReason.WRONG_DIRECTION.value: "direction",
    DecodeErrorReason.OUT_OF_RANGE.value: "range",
}
"""Decode error reasons as the header names them."""


@dataclass(frozen=True, slots=True)
class Alarm:
    key: Key | None
    at: float
    what: str


@dataclass(frozen=True, slots=True)
class Row:
    """One node on the screen."""

    key: Key
    label: str
    node: int
    level_uj: int | None
    level_source: str | None
    """``telemetry``, ``books`` or ``bound`` (at most, from the audit)."""
    flags: int
    joining: bool
    tx: int | None
    phase: Phase | None
    phase_age: float | None
    sends: int
    commits: int
    aborts: int
    write_offs: int
    returns: int
    returned_uj: int
    granted_uj: int
    last_outcome: Outcome | None
    outcome_age: float | None
    lost: bool
    alarms: int
    damaged: int
    frames: int
    last_frame_age: float | None
    books: BookNode | None


@dataclass(frozen=True, slots=True)
class Snapshot:
    now: float
    frames: int
    """``MonitorModel.frames`` at ``now``: the one frame count on the screen (header and corner)."""
    frames_per_s: float
    load: float | None
    """Fraction of the bus's time taken in the last window; None without a bit rate."""
    bitrate: int | None
    foreign: int
    foreign_by: dict[str, int]
    """``foreign`` by protocol (``canergy.inspect.others.protocol_of``)."""
    errors: dict[str, int]
    rows: tuple[Row, ...]
    books: Books | None
    usable_history: tuple[tuple[float, int], ...]
    """(time read, µJ) of the supervisor's usable budget, oldest first."""
    alarms: tuple[Alarm, ...]
    notes: tuple[str, ...]


class MonitorModel:
    def __init__(
        self,
        codec: Codec,
        *,
        bitrate: int | None = None,
        data_bitrate: int | None = None,
        lost_after_s: float = 3.0,
        reordered: bool = False,
        auth: CaptureAuth | None = None,
        window_s: float = 1.0,
        audit_segment: int = AUDIT_SEGMENT,
        namer: Namer | None = None,
    ) -> None:
        self.codec = codec
        self.bitrate, self.data_bitrate = bitrate, data_bitrate
        self.lost_after_s, self.window_s = lost_after_s, window_s
        self.reordered, self.audit_segment = reordered, audit_segment
        self._describe: Callable[[can.Message], Described] = (
            auth.describe if auth is not None else lambda f: describe(codec, f)
        )
        self.frames = 0
        """Every frame received from the bus or read from the capture, in one place: canergy's,
        foreign ones, error frames and those that failed to decode (CRC, DLC, MAC...) alike. The
        screen shows this count only (the header's ``frames`` and the title's corner, both from
        one ``Snapshot``); the feeds' own counters (``ReplayFeed.fed``, ``ModelListener.received``)
        pace the replay and measure the reader, never the screen."""
        self.foreign = 0
        self.namer = namer or Namer()
        self.foreign_by: Counter[str] = Counter()
        self.errors: Counter[str] = Counter()
        self.tracks: dict[Key, NodeTrack] = {}
        self.auditor = Auditor(reordered=reordered)
        self.alarm_counts: Counter[Key | None] = Counter()
        self.alarms: deque[Alarm] = deque(maxlen=ALARMS_KEPT)
        self._window: deque[tuple[float, float]] = deque()
        self._busy = 0.0
        """Bus seconds of the frames in ``_window``."""
        self.books: Books | None = None
        self.usable_history: deque[tuple[float, int]] = deque(maxlen=USABLE_HISTORY)
        self.notes: dict[str, str] = {}

    # -- frames -------------------------------------------------------------------------------
    def feed(self, frame: can.Message, t: float) -> None:
        self.frames += 1
        if self.frames % FREEZE_EVERY == 0:
            gc.freeze()
        busy = frame_seconds(frame, self.bitrate, self.data_bitrate) if self.bitrate else 0.0
        self._window.append((t, busy))
        self._busy += busy
        self._expire(t)
        d = self._describe(frame)
        if d.error_frame:
            self.errors["error frame"] += 1
        elif not d.ours:
            self.foreign += 1
            self.foreign_by[protocol_of(self.namer.named(d))] += 1
        elif d.mac == "BAD":
            self.errors["mac"] += 1
        elif (d.message is None and d.mac is None) or (d.message is not None and not d.crc_ok):
            self.errors[ERROR_LABELS.get(d.problem or "", d.problem or "?")] += 1
        if d.message is not None:
            key = (d.channel, d.message.node)
            track = self.tracks.get(key)
            if track is None:
                track = self.tracks[key] = NodeTrack(d.channel, d.message.node)
            track.feed(d if d.mac != "BAD" else replace(d, crc_ok=False), t)
        self._audit(d, t)

    def _audit(self, d: Described, t: float) -> None:
        auditor = self.auditor
        before = len(auditor.violations)
        auditor.feed(replace(d, message=None, crc_ok=None) if d.mac == "BAD" else d)
        for v in auditor.violations[before:]:
            self._alarm(v.channel, v.node, t, v.what)
        if auditor.frames >= self.audit_segment:
            before = len(auditor.violations)
            auditor.finish()
            for v in auditor.violations[before:]:
                self._alarm(v.channel, v.node, t, v.what)
            self.auditor = Auditor(reordered=self.reordered)

    def _alarm(self, channel: str, node: int | None, t: float, what: str) -> None:
        key = (channel, node) if node is not None else None
        self.alarm_counts[key] += 1
        self.alarms.append(Alarm(key, t, what))

    def _expire(self, now: float) -> None:
        window, edge = self._window, now - self.window_s
        while window and window[0][0] <= edge:
            self._busy -= window.popleft()[1]
        if not window:
            self._busy = 0.0  # no drift from float sums

    # -- other inputs -------------------------------------------------------------------------
    def note(self, topic: str, text: str | None) -> None:
        """A line for the header (a bus error, a capture problem); None clears the topic."""
        if text is None:
            self.notes.pop(topic, None)
        else:
            self.notes[topic] = text

    def set_books(self, books: Books) -> None:
        if books.error is None:
            self.usable_history.append((books.at, books.usable_uj))
            self.books = books
        elif self.books is None or self.books.error is not None:
            self.books = books
        else:  # keep the last good books, say why they are not fresh
            self.books = replace(self.books, error=books.error)

    # -- views --------------------------------------------------------------------------------
    def snapshot(self, now: float) -> Snapshot:
        self._expire(now)
        span = self.window_s
        return Snapshot(
            now=now,
            frames=self.frames,
            frames_per_s=len(self._window) / span,
            load=self._busy / span if self.bitrate else None,
            bitrate=self.bitrate,
            foreign=self.foreign,
            foreign_by=dict(self.foreign_by),
            errors=dict(self.errors),
            rows=tuple(self._rows(now)),
            books=self.books,
            usable_history=tuple(self.usable_history),
            alarms=tuple(self.alarms),
            notes=tuple(self.notes.values()),
        )

    def raw(self, key: Key, shown: Snapshot | None = None) -> tuple[list[Described], list[Alarm]]:
        """The latest frames of one node and its alarms; with ``shown``, as they were when that
        snapshot was taken (a paused screen's raw view is of its frozen moment, without the
        frames a bus kept bringing since)."""
        track = self.tracks.get(key)
        frames = list(track.raw) if track is not None else []
        if shown is None:
            return frames, [a for a in self.alarms if a.key == key]
        then = next((r.frames for r in shown.rows if r.key == key), 0)
        newer = track.frames - then if track is not None else 0
        frames = frames[: max(0, len(frames) - newer)]
        return frames, [a for a in shown.alarms if a.key == key]

    def _rows(self, now: float) -> list[Row]:
        channels = {channel for channel, _ in self.tracks}
        many = len(channels) > 1
        books = self.books.nodes if self.books is not None and self.books.nodes else {}
        matched: dict[Key, BookNode] = {}
        books_only: list[tuple[str, BookNode]] = []
        for name, entry in books.items():
            key = _books_key(name, channels)
            if key is not None and key in self.tracks:
                matched[key] = entry
            else:
                books_only.append((name, entry))
        rows = [
            self._row(track, f"{key[0]}/{key[1]}" if many else str(key[1]), now, matched.get(key))
            for key, track in self.tracks.items()
        ]
        for name, entry in books_only:
            bus, _, node_text = name.rpartition("/")
            if node_text.isdigit():
                rows.append(self._row(NodeTrack(bus, int(node_text)), name, now, entry))
        return rows

    def _row(self, track: NodeTrack, label: str, now: float, entry: BookNode | None) -> Row:
        key = (track.channel, track.node)
        level, source = track.level_uj, "telemetry" if track.level_uj is not None else None
        if level is None and entry is not None and entry.level_uj is not None:
            level, source = entry.level_uj, "books"
        if level is None:
            audited = self.auditor.nodes.get(key)
            bound = audited.holdable_bound() if audited is not None else None
            if bound is not None:
                level, source = max(0, bound), "bound"
        heard = track.heard
        lost = heard is None or now - heard > self.lost_after_s
        if entry is not None:
            lost = lost or entry.lost
        outcome = track.last_outcome
        return Row(
            key=key,
            label=label,
            node=track.node,
            level_uj=level,
            level_source=source,
            flags=track.flags,
            joining=track.joining,
            tx=track.tx,
            phase=track.phase,
            phase_age=now - track.opened if track.phase is not None else None,
            sends=track.sends,
            commits=track.commits,
            aborts=track.aborts,
            write_offs=track.write_offs,
            returns=track.returns,
            returned_uj=track.returned_uj,
            granted_uj=track.granted_uj,
            last_outcome=outcome,
            outcome_age=now - outcome.at if outcome is not None else None,
            lost=lost,
            alarms=self.alarm_counts.get(key, 0),
            damaged=track.damaged,
            frames=track.frames,
            last_frame_age=now - track.last_frame if track.last_frame is not None else None,
            books=entry,
        )


def _books_key(name: str, channels: set[str]) -> Key | None:
    """The track a status node name stands for: ``5`` is node 5 on the one channel seen,
    ``can1/5`` node 5 on channel ``can1``."""
    bus, _, node_text = name.rpartition("/")
    try:
        node = int(node_text)
    except ValueError:
        return None
    if bus:
        return (bus, node)
    if len(channels) == 1:
        return (next(iter(channels)), node)
    return None
