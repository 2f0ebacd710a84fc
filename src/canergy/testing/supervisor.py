"""A ``canergy supervisor`` started for a test, driven through its control socket.

On python-can's virtual bus it runs in a thread of the test's process (the virtual bus connects
only one process's buses); on any other interface as a process of its own. Either way it is the
command as users run it, with the flags given, its state and status files and its control
socket in the test's directory.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from canergy.live.supervisor.control import MAX_SOCKET_PATH, MAX_STATUS, NoSupervisor, request
from canergy.testing.bus import Process, TestBus
from canergy.testing.run import until
from canergy.units import parse_energy

START_S = 30.0
"""How long a start may take (a process in user-mode Linux: several seconds)."""


class SupervisorRun:
    """The supervisor of ``bus`` started with ``flags`` (as ``canergy supervisor`` takes them,
    e.g. ``["--nodes", "1-3", "--initial", "10J", "--target", "1J"]``) plus ``--state``,
    ``--status-file`` and ``--control`` in ``tmp``; ``auth``: authenticated mode with a master
    key it makes (``node_key(n)`` for each node's)."""

    def __init__(
        self,
        bus: TestBus,
        tmp: Path,
        flags: Sequence[str],
        name: str = "supervisor",
        auth: bool = False,
    ):
        self.bus, self.name, self.tmp = bus, name, tmp
        self.master_key: Path | None = None
        if auth:  # a master key of its own; node_key(n) derives each node's
            from canergy.auth.keys import new_master, write_key

            self.master_key = tmp / f"{name}-master.key"
            write_key(self.master_key, new_master(1))
            flags = [*flags, "--auth", str(self.master_key)]
        self.state = tmp / f"{name}-state.json"
        self.status_file = tmp / f"{name}-status.json"
        self.control = tmp / f"{name}.sock"
        self._socket_dir: Path | None = None
        if len(str(self.control).encode()) > MAX_SOCKET_PATH:  # a deep tmp_path
            self._socket_dir = Path(tempfile.mkdtemp(prefix="canergy-"))
            self.control = self._socket_dir / f"{name}.sock"
        self.argv = [
            *("supervisor", *bus.flags, *flags),
            *("--state", str(self.state), "--status-file", str(self.status_file)),
            *("--control", str(self.control), "--no-fsync"),
        ]
        self.exit_status: int | None = None
        self.process: Process | None = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        if bus.interface == "virtual":
            self._thread = threading.Thread(target=self._serve, name=name, daemon=True)
            self._thread.start()
        else:
            self.process = Process(name, [sys.executable, "-m", "canergy", *self.argv], tmp)
        self._wait_listening()

    def _serve(self) -> None:
        from canergy.cli import main

        try:
            self.exit_status = main(self.argv)
        except BaseException as exc:  # argparse's SystemExit for a bad flag, or a crash
            self._error = exc

    def _ended(self) -> str | None:
        """Why it is no longer running (None while it runs)."""
        if self.process is not None:
            code = self.process.popen.poll()
            return None if code is None else f"exit {code}: {self.process.stderr()}"
        assert self._thread is not None
        if self._thread.is_alive():
            return None
        return f"exit {self.exit_status}" if self._error is None else repr(self._error)

    def _wait_listening(self) -> None:
        deadline = time.monotonic() + START_S
        while True:
            try:
                request(self.control, {"status": True}, 5, max_answer=MAX_STATUS)
                return
            except (NoSupervisor, ConnectionError):
                pass
            ended = self._ended()
            if ended is not None:
                raise RuntimeError(f"canergy {' '.join(self.argv)}: did not start ({ended})")
            if time.monotonic() > deadline:
                raise RuntimeError(f"{self.name}: no control socket after {START_S:g} s")
            time.sleep(0.02)

    def node_key(self, node: int) -> Path:
        """Node ``node``'s key file (``--auth`` of the node), derived from this supervisor's
        master key (started with ``auth=True``) and written once, mode 0600."""
        from canergy.auth.keys import load_key, node_key_of, write_key

        if self.master_key is None:
            raise ValueError(f"{self.name} runs without --auth: start it with auth=True")
        path = self.tmp / f"{self.name}-node-{node:03d}.key"
        if not path.exists():
            write_key(path, node_key_of(load_key(self.master_key), node))
        return path

    def grant(self, node: int | str, amount: int | str, timeout_s: float = 30) -> dict[str, Any]:
        """Grant ``amount`` (µJ, or an energy such as ``"0.5J"``) to ``node``, as ``canergy
        grant --control`` does; the supervisor's answer (``outcome``, or ``error``)."""
        uj = parse_energy(amount) if isinstance(amount, str) else amount
        return request(self.control, {"grant": {"node": node, "amount_uj": uj}}, timeout_s)

    def status(self) -> dict[str, Any]:
        """Its status now (after ``stop``: the last one it wrote)."""
        if self.exit_status is not None or (self._ended() is not None):
            data: dict[str, Any] = json.loads(self.status_file.read_text())
            return data
        return request(self.control, {"status": True}, 30, max_answer=MAX_STATUS)

    def wait_for(
        self, condition: Callable[[dict[str, Any]], bool], what: str = "", timeout_s: float = 60
    ) -> dict[str, Any]:
        """Poll the status until ``condition(status)``; the status then. ``AssertionError``
        naming ``what`` (and showing the status) after ``timeout_s``."""
        last: list[dict[str, Any]] = []

        def holds() -> bool:
            last[:] = [self.status()]
            return condition(last[0])

        def show() -> str:
            return json.dumps(last[0].get("nodes", last[0]), sort_keys=True)[:2000]

        until(holds, what, timeout_s, show, period_s=0.05)
        return last[0]

    def intrusions(self) -> dict[str, Any]:
        """Foreign frames seen so far (the status's ``intrusions`` report)."""
        report: dict[str, Any] = self.status().get("intrusion_report", {})
        return report

    def stop(self, timeout_s: float = 60) -> int:
        """Stop it as SIGTERM would (it settles open transactions first); its exit status."""
        if self.process is not None:  # SIGTERM, as a user stops it
            self.exit_status = self.process.stop(timeout_s=timeout_s)
        else:
            assert self._thread is not None
            if self._thread.is_alive():
                with contextlib.suppress(ConnectionError):  # it stopped meanwhile
                    request(self.control, {"stop": True}, timeout_s)
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                raise AssertionError(f"{self.name} did not stop within {timeout_s:g} s")
            if self._error is not None:
                raise AssertionError(f"{self.name} ended with {self._error!r}")
        if self._socket_dir is not None:
            shutil.rmtree(self._socket_dir, ignore_errors=True)
        assert self.exit_status is not None
        return self.exit_status
