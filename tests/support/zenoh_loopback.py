"""Zenoh sessions that stay on this machine: a free loopback port, its endpoint, a fresh site.

A test's sessions listen on or connect to ``tcp/127.0.0.1:<free port>`` only, so nothing leaves
this machine, on a site name of their own, so no two tests share one.
"""

from __future__ import annotations

import socket
import uuid


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def site() -> str:
    return f"t-{uuid.uuid4().hex[:12]}"


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"
