"""The serve loop of every long-running process on a bus: the supervisor, the gateway and the
node emulator poll their bus loop until they are done, SIGINT/SIGTERM ask them to stop, and
between polls each does its own periodic work (control requests, status files)."""

from __future__ import annotations

import inspect
import queue
import signal
import threading
import weakref
from collections.abc import Callable
from typing import Any, Protocol

from canergy.live.runtime import monotonic_us
from canergy.live.supervisor.control import ControlServer
from canergy.live.supervisor.service import SupervisorService

POLL_S = 0.05
"""The longest a poll waits for a frame: the latency of periodic work and of a stop."""


class Pollable(Protocol):
    def poll(self, max_wait_s: float = 0.1) -> None: ...


def serve(
    loop: Pollable,
    done: Callable[[int], bool],
    stop: Callable[[int], None],
    each: Callable[[int], None] | None = None,
) -> None:
    """Poll ``loop`` until ``done(now)``. SIGINT and SIGTERM call ``stop(now)`` (when this runs
    in the main thread; they stay set after, a second signal harmless while the caller winds
    up, but hold a bound ``stop`` weakly: a handler keeps nothing served alive, such as a
    core that keeps a state file locked); ``each(now)`` runs after every poll."""
    stop_ref = weakref.WeakMethod(stop) if inspect.ismethod(stop) else lambda: stop

    def on_signal(signum: int, frame: object) -> None:
        live = stop_ref()
        if live is not None:
            live(monotonic_us())

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, on_signal)
        signal.signal(signal.SIGTERM, on_signal)
    while not done(monotonic_us()):
        loop.poll(POLL_S)
        if each is not None:
            each(monotonic_us())


def serve_supervisor(
    loop: Pollable,
    service: SupervisorService,
    control: ControlServer | None,
    until: Callable[[], bool] | None = None,
    manager: Any = None,
    exit: Callable[[], None] | None = None,
) -> None:
    """A supervisor (or a gateway's downstream): serve until a signal, ``until()`` or a control
    request stops it and it has settled; answer control requests; with CANopen (``manager``)
    tell it of rebooted nodes. Then ``exit()`` (``RunningSupervisor.exit``: the guarded
    devices halted and metered) and the last status."""

    posted: queue.SimpleQueue[Callable[[], None]] = queue.SimpleQueue()
    """Work other threads hand to this one: only the loop thread touches the books."""

    def each(now: int) -> None:
        while not posted.empty():
            posted.get_nowait()()
        if manager is not None and not service.config.listen_only:
            for node in manager.rebooted():
                service.node_rebooted(node, now)
        if control is not None:
            for req, reply in control.pending():
                answer_control(service, req, reply, manager, posted.put)
        if until is not None and until():
            service.stop(now)

    serve(loop, service.finished, service.stop, each)
    if exit is not None:
        exit()
    service.write_status()


def answer_control(
    service: SupervisorService,
    req: dict[str, Any],
    reply: Any,
    manager: Any = None,
    post: Callable[[Callable[[], None]], None] | None = None,
) -> None:
    """One request on the control socket: a grant, the status, a stop, or (with CANopen) the
    SDO audit, whose comparison with the books ``post`` hands back to the loop thread."""
    from canergy.bus_keys import parse_node_name

    if req.get("audit") is True:
        if manager is None:
            reply({"error": "the SDO audit needs --canopen"})
            return
        if post is None:
            reply({"error": "the SDO audit needs the serve loop"})
            return
        from canergy.live.canopen.manager import compare

        def read_then_compare() -> None:  # SDO reads block: off the loop, which keeps running
            readings = manager.read_energy()
            post(lambda: reply(compare(readings, service.ledger.books())))

        threading.Thread(target=read_then_compare, daemon=True).start()
        return
    if req.get("status") is True:
        reply(service.status())
        return
    if req.get("stop") is True:
        service.stop(monotonic_us())
        reply({"stopping": True})
        return
    grant = req.get("grant")
    if not isinstance(grant, dict):
        reply(
            {
                "error": 'expected {"grant": {"node": N, "amount_uj": A}}, {"status": true} or '
                '{"stop": true}'
            }
        )
        return
    node, amount = grant.get("node"), grant.get("amount_uj")
    buses = service.config.bus_names
    if not isinstance(amount, int) or isinstance(amount, bool) or amount <= 0:
        reply({"error": "amount_uj must be a positive integer"})
        return
    try:
        key = parse_node_name(buses, node)
    except ValueError as exc:
        reply({"error": str(exc)})
        return
    service.request_grant(key, amount, reply)
