"""Zenoh sessions that stay on this machine: a free loopback port, its endpoint (the pytest
plugin's ``free_port`` and ``loopback``), a fresh site.

A test's sessions listen on or connect to ``tcp/127.0.0.1:<free port>`` only, so nothing leaves
this machine, on a site name of their own, so no two tests share one.
"""

from __future__ import annotations

import uuid

from canergy.testing.bus import free_port
from canergy.testing.bus import loopback as endpoint

__all__ = ["endpoint", "free_port", "site"]


def site() -> str:
    return f"t-{uuid.uuid4().hex[:12]}"
