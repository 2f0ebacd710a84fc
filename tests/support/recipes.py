"""The recipes of the README and of the site's pages as tests: their marked shell blocks, run
as written (``support.readme.pages()``: README.md, then docs/).

A shell block preceded by ``<!-- recipe: SESSION WHERE -->`` is a recipe. WHERE is ``local``
(python-can's virtual bus or no bus: the normal suite), ``vcan`` (real SocketCAN on vcan0 and
vcan1: the vcan suite) or ``virtual`` (a bench command for a real bus that
tests/test_drive_recipes.py runs in process on python-can's virtual bus, emulators standing in
for the devices; not by ``run_session``). The recipes of one session run in page order (README
first, then the site's pages by path) in one working directory, as a user would type them in one
shell: each line is a command (``\\`` continues it, ``#`` starts a comment); a line ending in
``&`` runs in the background, as in another terminal, and is waited for until its ``--control``
socket and ``--status-file`` exist (one with neither: until it holds a socket, its bus, which it
opens after it has set its Ctrl-C handler; a SIGINT during its imports would end it with a
traceback); any other line must exit 0 within ``FOREGROUND_S``. When the session ends, or before
a recipe marked ``stopped`` (one that reads what the processes wrote once they were stopped),
its background processes get SIGINT, as Ctrl-C would give them, and must exit 0.

The working directory holds links to the repository's ``dbc``, ``firmware``, ``firmware_model``
and ``scripts``, so paths in the pages resolve as in a checkout; ``canergy`` and ``python`` are
the venv's. ``sessions`` groups the recipes of one WHERE by session and ``run_session`` runs one
(tests/test_readme_recipes.py and tests/test_vcan_readme.py).
"""

from __future__ import annotations

import os
import re
import shlex
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from support.readme import ROOT, page_name, pages

MARK = re.compile(
    r"^( *)<!-- recipe: (\S+) (local|vcan|virtual)( stopped)? -->\n\1```sh\n(.*?)^\1```",
    re.S | re.M,
)
LINKED = ("dbc", "firmware", "firmware_model", "scripts")
FOREGROUND_S = 900.0
"""The longest recipes (prove, sweep) took 41-63 s each in the suite on a 2-core machine: room
for a far slower one."""
READY_S = 60.0
STOP_S = 60.0


@dataclass(frozen=True)
class Command:
    text: str
    line: int
    background: bool
    page: str = "README.md"
    """The page it is written on (its path in the repository), for failures."""

    @property
    def argv(self) -> list[str]:
        return shlex.split(self.text)

    def waits_for(self) -> list[str]:
        """The files a background command makes once it is up: its socket and status file."""
        argv = self.argv
        return [argv[i + 1] for i, a in enumerate(argv[:-1]) if a in ("--control", "--status-file")]


@dataclass(frozen=True)
class Recipe:
    session: str
    where: str
    line: int
    commands: tuple[Command, ...]
    stopped: bool = False
    """Runs once the session's background processes have stopped."""


def recipes(text: str | None = None, page: str = "README.md") -> list[Recipe]:
    """Every marked block of ``text`` (on ``page``), in order; without ``text``, of every page
    (``support.readme.pages()``)."""
    if text is None:
        return [r for path in pages() for r in recipes(path.read_text(), page_name(path))]
    found = []
    for m in MARK.finditer(text):
        first = text[: m.start(5)].count("\n") + 1
        commands = tuple(_commands(textwrap.dedent(m.group(5)), first, page))
        found.append(Recipe(m.group(2), m.group(3), first, commands, bool(m.group(4))))
    return found


def _commands(block: str, first: int, page: str) -> list[Command]:
    out: list[Command] = []
    pending, start = "", first
    for number, raw in enumerate(block.splitlines(), first):
        if not pending:
            start = number
        code = _without_comment(raw)
        if code.rstrip().endswith("\\"):
            pending += code.rstrip()[:-1] + " "
            continue
        text = (pending + code).strip()
        pending = ""
        if not text:
            continue
        background = text.endswith("&")
        out.append(Command(text.rstrip("&").strip(), start, background, page))
    return out


def _without_comment(line: str) -> str:
    """The line up to a ``#`` that starts a comment (not one inside quotes or a word)."""
    quote = ""
    for i, ch in enumerate(line):
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1].isspace()):
            return line[:i]
    return line


@dataclass
class Session:
    """One session's working directory and background processes."""

    cwd: Path
    log: list[str] = field(default_factory=list)
    background: list[tuple[Command, subprocess.Popen[bytes], Path]] = field(default_factory=list)

    def __post_init__(self) -> None:
        for name in LINKED:
            link = self.cwd / name
            if not link.exists():
                link.symlink_to(ROOT / name)
        venv_bin = str(Path(sys.executable).parent)
        self.env = {
            **os.environ,
            "PATH": f"{venv_bin}{os.pathsep}{os.environ.get('PATH', '')}",
            "PYTHONUNBUFFERED": "1",
            "COLUMNS": "100",
        }

    def run(self, recipe: Recipe) -> None:
        if recipe.stopped:
            self.close()
        for command in recipe.commands:
            if command.background:
                self._start(command)
            else:
                self._run(command)

    def _where(self, command: Command) -> str:
        return f"{command.page}:{command.line}: {command.text}"

    def _start(self, command: Command) -> None:
        out = self.cwd / f"background-{len(self.background)}.log"
        with out.open("wb") as sink:
            proc = subprocess.Popen(  # exec: SIGINT reaches the program, not a shell
                ["bash", "-c", f"exec {command.text}"],
                cwd=self.cwd,
                env=self.env,
                stdout=sink,
                stderr=subprocess.STDOUT,
            )
        self.background.append((command, proc, out))
        end = time.monotonic() + READY_S
        waits: list[tuple[str, Callable[[], bool]]] = [
            (f"never made {name}", (self.cwd / name).exists) for name in command.waits_for()
        ] or [("never opened its bus", lambda: _holds_socket(proc.pid))]
        for failure, up in waits:
            while not up():
                if proc.poll() is not None:
                    raise AssertionError(
                        f"{self._where(command)}\nended with {proc.returncode} before it was "
                        f"up:\n{out.read_text()[-3000:]}"
                    )
                assert time.monotonic() < end, f"{self._where(command)}\n{failure}"
                time.sleep(0.05)

    def _run(self, command: Command) -> None:
        proc = subprocess.Popen(  # a session of its own: a timeout ends its workers too
            ["bash", "-o", "pipefail", "-c", command.text],
            cwd=self.cwd,
            env=self.env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        try:
            out, _ = proc.communicate(timeout=FOREGROUND_S)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            out, _ = proc.communicate()
            raise AssertionError(
                f"{self._where(command)}\nstill running after {FOREGROUND_S:.0f} s:\n"
                f"{out.decode(errors='replace')[-3000:]}"
            ) from None
        shown = out.decode(errors="replace")
        self.log.append(f"$ {command.text}\n{shown}")
        assert proc.returncode == 0, (
            f"{self._where(command)}\nexit {proc.returncode}:\n{shown[-3000:]}\n"
            f"background:\n{self.background_output()}"
        )

    def background_output(self) -> str:
        return "\n".join(
            f"--- {command.text}\n{out.read_text()[-2000:]}" for command, _, out in self.background
        )

    def close(self) -> None:
        """SIGINT to every background process at once, as Ctrl-C gives a terminal's process
        group; each must exit 0."""
        failures = []
        for _, proc, _ in self.background:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for command, proc, out in self.background:
            try:
                code = proc.wait(timeout=STOP_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                code = proc.wait()
            if code != 0:
                failures.append(f"{self._where(command)}\nexit {code}:\n{out.read_text()[-3000:]}")
        self.background.clear()
        assert not failures, "\n".join(failures)


def sessions(where: str) -> dict[str, list[Recipe]]:
    found: dict[str, list[Recipe]] = {}
    for recipe in recipes():
        if recipe.where == where:
            found.setdefault(recipe.session, []).append(recipe)
    return found


def run_session(blocks: list[Recipe], tmp_path: Path) -> Session:
    session = Session(tmp_path)
    try:
        for recipe in blocks:
            session.run(recipe)
    finally:
        session.close()
    return session


def _holds_socket(pid: int) -> bool:
    """Whether process ``pid`` has a socket open (/proc/PID/fd)."""
    fds = Path(f"/proc/{pid}/fd")
    try:
        links = [os.readlink(fd) for fd in fds.iterdir()]
    except OSError:  # gone, or an fd closed while read
        return False
    return any(link.startswith("socket:") for link in links)
