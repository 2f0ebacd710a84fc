"""A python-can bus whose frames travel between hosts as Eclipse Zenoh samples.

Open it as ``can.Bus(interface="zenoh", channel=SITE, listen=..., connect=..., mode=...)`` or,
from any canergy command, ``-i zenoh -c SITE --bus-kwargs listen=tcp/127.0.0.1:7447``.

Every frame is one sample on the key ``canergy/<site>/<id>``: the identifier in upper-case hex,
8 digits for a 29-bit (extended) one, 3 for an 11-bit one. The payload (``encode_frame``)::

    byte 0      flags: 0x01 extended, 0x02 remote, 0x04 CAN FD, 0x08 bit-rate switch,
                0x10 error frame, 0x20 error-state indicator, 0x80 timestamp follows
                (0x40 reserved, zero)
    bytes 1-8   sender: 8 random bytes drawn per bus object
    byte 9      length: data bytes; for a remote frame the requested DLC (no data follows)
    bytes 10-   data
    last 8      with 0x80: the sender's send time, big-endian IEEE-754 seconds since the epoch

A bus drops the frames it sent itself (python-can's ``receive_own_messages=False``) by the sender
field, so two bus objects in one process are two participants. The codec, CRC, dump, decode and
audit see the same frames as on a wire.

Safety: multicast scouting and gossip are always disabled; a session only listens on and
connects to the explicit unicast ``tcp/`` or ``udp/`` endpoints given, and a multicast address
is refused.
"""

from __future__ import annotations

import ipaddress
import json
import re
import secrets
import struct
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import can

from canergy.extras import MissingExtra

try:
    import zenoh
    import zenoh.handlers
except ImportError as exc:  # canergy[zenoh]; python-can reports it as the interface's error
    raise MissingExtra("zenoh", exc) from exc

KEY_PREFIX = "canergy"
SENDER_BYTES = 8
FLAG_EXTENDED = 0x01
FLAG_REMOTE = 0x02
FLAG_FD = 0x04
FLAG_BRS = 0x08
FLAG_ERROR = 0x10
FLAG_ESI = 0x20
FLAG_TIMESTAMP = 0x80
_KNOWN_FLAGS = 0xBF
_HEADER = struct.Struct(f">B{SENDER_BYTES}sB")
_TIMESTAMP = struct.Struct(">d")
_FD_LENGTHS = frozenset((*range(9), 12, 16, 20, 24, 32, 48, 64))
_SITE = re.compile(r"[A-Za-z0-9_.-]+")
_ENDPOINT = re.compile(r"(tcp|udp)/(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]+):([0-9]{1,5})")
_MAX_PUBLISHERS = 4096


class MalformedFrame(ValueError):
    """A sample that is not a canergy frame in this encoding."""


@dataclass(frozen=True, slots=True)
class WireFrame:
    """A decoded sample: the frame, who sent it and when (sender's clock, if given)."""

    message: can.Message
    sender: bytes
    sent_at: float | None


def frame_key(site: str, arbitration_id: int, extended: bool) -> str:
    """``canergy/<site>/<id>``: 8 hex digits for an extended identifier, 3 for a standard one."""
    digits = f"{arbitration_id:08X}" if extended else f"{arbitration_id:03X}"
    return f"{KEY_PREFIX}/{site}/{digits}"


def encode_frame(msg: can.Message, sender: bytes, sent_at: float | None = None) -> bytes:
    """The sample payload of ``msg`` (see the module docstring)."""
    flags = (
        (FLAG_EXTENDED if msg.is_extended_id else 0)
        | (FLAG_REMOTE if msg.is_remote_frame else 0)
        | (FLAG_FD if msg.is_fd else 0)
        | (FLAG_BRS if msg.bitrate_switch else 0)
        | (FLAG_ERROR if msg.is_error_frame else 0)
        | (FLAG_ESI if msg.error_state_indicator else 0)
        | (FLAG_TIMESTAMP if sent_at is not None else 0)
    )
    data = b"" if msg.is_remote_frame else bytes(msg.data)
    length = msg.dlc if msg.is_remote_frame else len(data)
    tail = b"" if sent_at is None else _TIMESTAMP.pack(sent_at)
    return _HEADER.pack(flags, sender, length) + data + tail


def decode_frame(key: str, payload: bytes, site: str) -> WireFrame:
    """The frame a sample on ``key`` carries; ``MalformedFrame`` when it is none."""
    prefix = f"{KEY_PREFIX}/{site}/"
    if not key.startswith(prefix):
        raise MalformedFrame(f"key {key!r} is not under {prefix!r}")
    digits = key[len(prefix) :]
    if len(digits) not in (3, 8) or not all(c in "0123456789ABCDEF" for c in digits):
        raise MalformedFrame(f"key {key!r} does not end in 3 or 8 upper-case hex digits")
    if len(payload) < _HEADER.size:
        raise MalformedFrame(f"payload of {len(payload)} bytes is shorter than its header")
    flags, sender, length = _HEADER.unpack_from(payload)
    extended, remote, fd = (bool(flags & f) for f in (FLAG_EXTENDED, FLAG_REMOTE, FLAG_FD))
    if flags & ~_KNOWN_FLAGS & 0xFF:
        raise MalformedFrame(f"unknown flags 0x{flags:02X}")
    if extended != (len(digits) == 8):
        raise MalformedFrame(f"key {key!r} disagrees with the extended flag")
    arbitration_id = int(digits, 16)
    if arbitration_id > (0x1FFFFFFF if extended else 0x7FF):
        raise MalformedFrame(f"identifier 0x{arbitration_id:X} out of range")
    if (remote and (fd or length > 8)) or length not in (_FD_LENGTHS if fd else range(9)):
        raise MalformedFrame(f"length {length} with flags 0x{flags:02X}")
    data_len = 0 if remote else length
    expected = _HEADER.size + data_len + (_TIMESTAMP.size if flags & FLAG_TIMESTAMP else 0)
    if len(payload) != expected:
        raise MalformedFrame(f"payload of {len(payload)} bytes, expected {expected}")
    end = _HEADER.size + data_len
    sent_at = _TIMESTAMP.unpack_from(payload, end)[0] if flags & FLAG_TIMESTAMP else None
    message = can.Message(
        arbitration_id=arbitration_id,
        is_extended_id=extended,
        is_remote_frame=remote,
        is_error_frame=bool(flags & FLAG_ERROR),
        is_fd=fd,
        bitrate_switch=bool(flags & FLAG_BRS),
        error_state_indicator=bool(flags & FLAG_ESI),
        dlc=length,
        data=None if remote else payload[_HEADER.size : end],
        channel=site,
    )
    return WireFrame(message, sender, sent_at)


def parse_endpoints(value: str | Sequence[str] | None, *, role: str) -> list[str]:
    """Explicit unicast ``tcp/HOST:PORT`` or ``udp/HOST:PORT`` endpoints (a comma-separated
    string or a sequence); anything multicast, or any other form, raises ``ValueError``."""
    if value is None:
        return []
    items = value.split(",") if isinstance(value, str) else list(value)
    endpoints = []
    for item in (str(i).strip() for i in items):
        if not item:
            continue
        match = _ENDPOINT.fullmatch(item)
        if "multicast" in item.lower() or match is None:
            raise ValueError(
                f"zenoh {role} endpoint {item!r}: only unicast tcp/HOST:PORT or udp/HOST:PORT"
            )
        host, port = match[2].strip("[]"), int(match[3])
        try:
            address = ipaddress.ip_address(host)
        except ValueError:
            address = None  # a host name
        if address is not None and address.is_multicast:
            raise ValueError(f"zenoh {role} endpoint {item!r}: multicast addresses are refused")
        if port > 65535 or (port == 0 and role == "connect"):
            raise ValueError(f"zenoh {role} endpoint {item!r}: bad port")
        endpoints.append(item)
    return endpoints


def zenoh_config(mode: str, listen: Sequence[str], connect: Sequence[str]) -> zenoh.Config:
    """A session configuration with multicast scouting and gossip off and only these
    endpoints (``parse_endpoints`` has checked them)."""
    if mode not in ("peer", "client"):
        raise ValueError(f"zenoh mode {mode!r}: peer or client")
    if mode == "client" and (listen or not connect):
        raise ValueError("zenoh client mode takes connect= endpoints and no listen=")
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("scouting/gossip/enabled", "false")
    config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return config


class ZenohBus(can.BusABC):
    """python-can bus over a Zenoh session; channel = site name, received from a subscriber on
    ``canergy/<site>/*``.

    ``listen``/``connect``: unicast endpoints (comma-separated); ``mode``: ``peer`` (default)
    or ``client``; ``fd``: allow sending CAN FD frames; ``receive_own_messages``: also return
    frames this bus sent; ``rx_queue_size``: frames kept for ``recv`` (oldest dropped beyond,
    counted in ``rx_overruns``). Multicast scouting and gossip are always off: with no
    endpoint the session reaches nobody. ``state`` is always ``BusState.ACTIVE`` (there is no
    controller). Other keyword arguments (``bitrate``...) are ignored.
    """

    def __init__(
        self,
        channel: can.typechecking.Channel,
        can_filters: can.typechecking.CanFilters | None = None,
        *,
        listen: str | Sequence[str] | None = None,
        connect: str | Sequence[str] | None = None,
        mode: str = "peer",
        fd: bool = False,
        receive_own_messages: bool = False,
        rx_queue_size: int = 10_000,
        **kwargs: Any,
    ) -> None:
        site = str(channel) if channel is not None else ""
        if not _SITE.fullmatch(site):
            raise ValueError(f"zenoh channel (site) {site!r}: letters, digits, '_', '.', '-'")
        config = zenoh_config(
            mode, parse_endpoints(listen, role="listen"), parse_endpoints(connect, role="connect")
        )
        self.site = site
        self.fd = bool(fd)
        self.receive_own_messages = bool(receive_own_messages)
        self.sender = secrets.token_bytes(SENDER_BYTES)
        self.channel_info = f"zenoh {KEY_PREFIX}/{site} ({mode})"
        self.rx_overruns = 0
        self.malformed = 0
        self._rx: deque[can.Message] = deque(maxlen=max(1, int(rx_queue_size)))
        self._ready = threading.Condition()
        self._closed = False
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._dropped = threading.Event()
        self._callback_thread: threading.Thread | None = None
        try:
            self._session = zenoh.open(config)
        except zenoh.ZError as exc:
            raise can.CanInitializationError(f"zenoh session: {exc}") from exc
        try:
            handler = zenoh.handlers.Callback(self._on_sample, self._on_drop)
            self._subscriber = self._session.declare_subscriber(f"{KEY_PREFIX}/{site}/*", handler)
            super().__init__(channel=site, can_filters=can_filters, **kwargs)
        except BaseException:
            self._session.close()  # type: ignore[no-untyped-call]
            raise
        if self.fd:
            self._can_protocol = can.CanProtocol.CAN_FD

    # -- receiving (zenoh's callback thread) ------------------------------------------------
    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            wire = decode_frame(str(sample.key_expr), sample.payload.to_bytes(), self.site)
        except MalformedFrame:
            self.malformed += 1
            return
        own = wire.sender == self.sender
        if own and not self.receive_own_messages:
            return
        wire.message.timestamp = time.time()
        wire.message.is_rx = not own
        with self._ready:
            if len(self._rx) == self._rx.maxlen:
                self.rx_overruns += 1
            self._rx.append(wire.message)
            self._ready.notify()

    def _on_drop(self) -> None:
        self._callback_thread = threading.current_thread()
        self._dropped.set()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        with self._ready:
            if not self._rx and not self._closed:
                self._ready.wait(timeout)
            if self._closed:
                raise can.CanOperationError("the zenoh bus is shut down")
            return (self._rx.popleft() if self._rx else None), False

    # -- sending ------------------------------------------------------------------------------
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Publish ``msg``. A full link queue makes this wait rather than drop (zenoh's
        dropping policy loses bursts on a loaded host); zenoh closes a link stuck for 5 s.
        ``timeout`` is not used."""
        if self._closed:
            raise can.CanOperationError("the zenoh bus is shut down")
        if msg.is_fd and not self.fd:
            raise can.CanOperationError("a CAN FD frame on a bus opened without fd=True")
        key = frame_key(self.site, msg.arbitration_id, msg.is_extended_id)
        payload = encode_frame(msg, self.sender, time.time())
        try:
            publisher = self._publishers.get(key)
            if publisher is None and len(self._publishers) < _MAX_PUBLISHERS:
                publisher = self._session.declare_publisher(
                    key, congestion_control=zenoh.CongestionControl.BLOCK, express=True
                )
                self._publishers[key] = publisher
            if publisher is None:
                self._session.put(
                    key, payload, congestion_control=zenoh.CongestionControl.BLOCK, express=True
                )
            else:
                publisher.put(payload)
        except zenoh.ZError as exc:
            raise can.CanOperationError(f"zenoh publish on {key}: {exc}") from exc

    def shutdown(self) -> None:
        """Undeclare everything, wait for the callback thread to end and close the session."""
        if self._closed:
            return
        super().shutdown()
        with self._ready:
            self._closed = True
            self._ready.notify_all()
        for publisher in self._publishers.values():
            publisher.undeclare()  # type: ignore[no-untyped-call]
        self._publishers.clear()
        self._subscriber.undeclare()  # type: ignore[no-untyped-call]
        thread = self._callback_thread if self._dropped.wait(10) else None
        if thread is not None and thread is not threading.current_thread():
            thread.join(10)
        self._session.close()  # type: ignore[no-untyped-call]
