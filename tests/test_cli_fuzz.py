"""Every option of every command, drawn by hypothesis: whatever the values, a command ends with
exit status 0, 1 or 2, prints no traceback, leaves no thread or bus running and touches no file
but its declared outputs.

The commands and their options come from the argparse parsers themselves (``canergy``'s
sub-commands and ``python -m firmware_model``), so an option added later is fuzzed without
editing this file; a new path option counts as an input (never written) until it is listed in
``OUTPUTS``.

Each run calls the command's ``main`` in this process, in a fresh temporary directory holding a
few files, and compares the directory tree before and after. Commands that would run for a long
time, forever or on a bus still parse and validate everything, open their files and their bus
(python-can's ``virtual`` interface, the only one drawn: it touches no hardware and no network),
and are stopped at their first wait on the bus, or where their long computation would begin:
``_Started`` is raised there and the command's own clean-up runs. The model checker and the demo
really run, on a few states and transactions.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import io
import os
import signal
import stat
import sys
import tempfile
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any
from unittest import mock

import can
import can.interfaces.virtual
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

import canergy.bench.run
import canergy.bridge.link
import canergy.check
import canergy.cli.dump
import canergy.cli.simulate
import canergy.dbc
import canergy.demo
import canergy.live.devices.mit_forward
import canergy.prove.obligations
import canergy.rules_doc
import canergy.sim.sweep
import firmware_model.__main__ as firmware
import firmware_model.drive.__main__ as drive
from canergy.cli import build_parser
from canergy.cli import main as canergy_main
from canergy.live.atomic import lock_path
from canergy.live.bus_group import BusGroup
from canergy.live.runtime import BusRuntime
from firmware_model.drive.canopen_face import DriveFace

FIRMWARE = "firmware_model"
DRIVE = "firmware_model.drive"
EMULATORS = {FIRMWARE: firmware, DRIVE: drive}
"""``python -m`` commands beside canergy's own: their parser and ``main``."""
EXAMPLES = 30
"""Runs per command; ``derandomize``: the same ones every time."""
MORE_EXAMPLES = {"supervisor": 60, "grant": 60, FIRMWARE: 60, DRIVE: 40}
"""Commands with many options and start-up checks behind them."""


def _subcommands() -> dict[str, argparse.ArgumentParser]:
    (sub,) = (a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


PARSERS: dict[str, argparse.ArgumentParser] = {
    **_subcommands(),
    **{name: module.build_parser() for name, module in EMULATORS.items()},
}

OUTPUTS: dict[str, set[str]] = {
    "demo": {"log"},
    "dbc": {"output"},
    "rules": {"docs"},
    "bench": {"json"},
    "prove": {"json"},
    "dump": {"log"},  # -l: a file in "." (its dest "log" is then ".")
    "simulate": {"out"},
    "sweep": {"out"},
    "supervisor": {"state", "status_file", "control", "cia402_capture"},
    "grant": {"state"},
    "keys": {"output"},
    "bridge": {"status_file", "log"},
    FIRMWARE: {"nv", "status_file"},
    DRIVE: {"status_file"},
}
"""The options (argparse ``dest``) naming what a command may create or change: a file, or a
directory and everything under it. Any other path is only read."""

# --- the temporary directory every run starts from -------------------------------------------

CAPTURE = (
    "(1795329832.132122) virtual0 0CE00101#0201007D09000000 R\n"
    "(1795329832.132506) virtual0 0CE00901#0B0100 R\n"
    "not a frame\n"
)
FILES = {
    "capture.log": CAPTURE,
    "empty.db": "",
    "notes.txt": "hello\n",
    "profile.csv": "time_s,watts\n0,0.5\n1,0\n",
    "bad.csv": "0,inf\n",
    "sub/inner.log": CAPTURE,
    "bench.dbc": 'VERSION ""\nBU_:\nBO_ 1 Heartbeat: 8 Vector__XXX\n'
    ' SG_ Error : 0|32@1+ (1,0) [0|0] "" Vector__XXX\n',
}
PATHS = [
    *FILES,
    "sub",
    ".",
    "",
    "-",
    "new.json",
    "new.log",
    "typo.db",
    "out",
    "sub/new.nv",
    "missing/x.json",
]
"""Existing files and directories, and names of nothing (some in a directory that is missing),
drawn for every path option: the same name often comes up for two options of one run."""
FRESH = ["new.json", "new.log", "out"]

NUMBERS = [
    "0",
    "1",
    "2",
    "0.5",
    "-1",
    "inf",
    "-inf",
    "nan",
    "1e999",
    "9" * 25,
    "99999999999",
    "4294967296",
    "0x10",
    "0x0CE00000",
    "0x2010",
    "1-2",
    "401,178",
    "1.5s",
    "250ms",
    "10J",
    "2W",
    "all",
    "",
]
BUS_KWARGS = [["receive_own_messages=True"], ["rx_queue_size=abc"], ["x=1", "y=2"], ["nope"], ["="]]
"""python-can's --bus-kwargs, never ``interface=`` (that would leave the virtual bus)."""
TIMINGS = [
    ["f_clock=8000000", "brp=1", "tseg1=5", "tseg2=2", "sjw=1", "nof_samples=1"],
    ["f_clock=8000000"],
    ["f_clock=inf"],
    ["f_clock=99999999999999999999999", "brp=1", "tseg1=5", "tseg2=2", "sjw=1"],
    ["nope"],
]

_TEXT = st.text(
    st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"), max_size=6
)
"""Anything a shell could pass (no NUL, no lone surrogate)."""
_PATH = st.sampled_from(PATHS)
_BUS_WORDS = {
    "interface": ["virtual"],
    "bus_kwargs": BUS_KWARGS[0],
    "timing": TIMINGS[0],
    "bus": ["virtual:fuzz:1-2"],
    "channel_filters": ["fuzz,0CE00100:1FFFFF00,701~7FF"],
    "bus1_interface": ["virtual"],
    "bus2_interface": ["virtual"],
    "app_interface": ["virtual"],
    "partition": ["1s+2s"],
    "dbc": ["bench.dbc"],
    "mit_model": ["DM4310"],
}
"""python-can's bus flags that take free text (and ``supervisor --bus``, ``bridge``'s two buses
and ``--partition``, ``inline``'s application bus, ``--mit-model``'s ``[IDS:]MODEL`` list): a
value each accepts."""


def _fuzzed(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    return [
        a
        for a in parser._actions
        if not isinstance(a, argparse._HelpAction | argparse._VersionAction)
    ]


def _wild(action: argparse.Action) -> st.SearchStrategy[list[str]]:
    """Anything for one option (its argument words): mostly what it refuses."""
    if action.dest == "interface":
        return st.just(["virtual"])
    if action.dest == "bus_kwargs":
        return st.sampled_from(BUS_KWARGS)
    if action.dest == "timing":
        return st.sampled_from(TIMINGS)
    if action.choices is not None:
        return st.sampled_from([*sorted(map(str, action.choices)), "", "nope"]).map(lambda v: [v])
    if action.type is Path or not action.option_strings:
        return _PATH.map(lambda v: [v])
    anything = st.one_of(
        st.sampled_from(NUMBERS),
        st.integers(-(2**70), 2**70).map(str),
        st.floats().map(repr),
        _PATH,
        _TEXT,
    )
    return anything.map(lambda v: [v])


def _accepts(convert: Any, text: str) -> bool:
    try:
        convert(text)
    except (argparse.ArgumentTypeError, ValueError, TypeError):
        return False
    return True


def _valid(action: argparse.Action) -> list[list[str]]:
    """What the option's own parsing accepts among the drawn words, so that a run gets past
    argparse often enough to exercise the start-up checks behind it."""
    if action.dest in _BUS_WORDS:
        return [_BUS_WORDS[action.dest]]
    if action.choices is not None:
        return [[str(c)] for c in sorted(map(str, action.choices))]
    if action.type is Path or not action.option_strings:
        return [[p] for p in PATHS]
    if action.type in (None, str):
        return [["0"], ["x"]]
    return [[v] for v in NUMBERS if _accepts(action.type, v)]


def _flag(action: argparse.Action) -> str:
    longs = [o for o in action.option_strings if o.startswith("--")]
    return longs[0] if longs else action.option_strings[0]


@st.composite
def invocations(draw: st.DrawFn, name: str) -> list[str]:
    """Arguments for command ``name``: each option given or not, required ones mostly given,
    mostly one option of a mutually exclusive group, the bus always ``virtual``."""
    parser = PARSERS[name]
    wildness = draw(st.sampled_from([0, 0, 1, 3, 10]))  # in tenths: how often a value is wild
    density = draw(st.sampled_from([3, 3, 6, 9]))  # in tenths: how often an option is given

    def value(action: argparse.Action) -> list[str]:
        if draw(st.integers(0, 9)) < wildness:
            return draw(_wild(action))
        if action.type is Path and draw(st.booleans()):
            return [draw(st.sampled_from(FRESH))]  # often a name a run may create
        return draw(st.sampled_from(_valid(action)))

    group_of = {id(a): g for g in parser._mutually_exclusive_groups for a in g._group_actions}
    used_groups: set[int] = set()
    argv: list[str] = []
    positionals: list[str] = []
    for action in _fuzzed(parser):
        group = group_of.get(id(action))
        likely = action.required or (group is not None and group.required)
        roll = draw(st.integers(0, 9))  # 0, hypothesis's simplest draw, is the usual choice
        if action.dest == "interface":  # the bus is virtual, unless --bus names it
            give = not any(word.startswith("--bus=") for word in argv)
        elif group is not None and id(group) in used_groups:
            give = roll == 9
        else:
            give = roll != 9 if likely else roll >= 10 - density
        if not give:
            continue
        if group is not None:
            used_groups.add(id(group))
        if not action.option_strings:
            positionals += value(action)
        elif action.nargs == 0:
            argv.append(_flag(action))
        elif action.nargs in ("+", "*"):
            argv += [_flag(action), *value(action)]
        else:
            (word,) = value(action)
            flag = _flag(action)
            argv.append(f"{flag}={word}" if flag.startswith("--") else flag + word)
    return [*argv, "--", *positionals] if positionals else argv


# --- running one command -----------------------------------------------------------------------


class _Started(BaseException):  # not an error: the run got past its start-up checks
    """Raised where a command would wait on its bus or begin a long computation."""


def _stop(*args: object, **kwargs: object) -> Any:
    raise _Started


STARTED = "started"


@contextlib.contextmanager
def _bounded_commands() -> Iterator[None]:
    """Stop long, endless or bus-bound commands right after their start-up; shrink the model
    checker and the demo to a few states and transactions; stdin holds a small capture."""
    real_open = canergy.cli.dump.open_bus
    real_check = canergy.check.check
    real_demo = canergy.demo.run_demo

    def open_bus(args: argparse.Namespace, filters: list[dict[str, Any]]) -> Any:
        bus = real_open(args, filters)
        bus.recv = _stop  # canergy dump: its first wait for a frame
        return bus

    def check(*args: Any, **kwargs: Any) -> Any:
        kwargs["max_states"] = min(kwargs.get("max_states") or 40, 40)
        return real_check(*args, **kwargs)

    def run_demo(cfg: Any) -> Any:
        small = dataclasses.replace(cfg, transactions=min(cfg.transactions, 3), initial=10**6)
        return real_demo(small)

    patches = [
        mock.patch.object(BusRuntime, "poll", _stop),  # supervisor, grant, firmware_model
        mock.patch.object(BusGroup, "poll", _stop),  # supervisor --bus
        mock.patch.object(canergy.bridge.link.Bridge, "poll", _stop),  # bridge
        mock.patch.object(canergy.live.devices.mit_forward.MitForwarder, "poll", _stop),  # inline
        mock.patch.object(DriveFace, "run", _stop),  # firmware_model.drive
        mock.patch.object(canergy.cli.dump, "open_bus", open_bus),
        mock.patch.object(canergy.check, "check", check),
        mock.patch.object(canergy.demo, "run_demo", run_demo),
        mock.patch.object(
            canergy.dbc, "dbc_text", lambda base, auth=None: f'VERSION "{base:#x} {auth}"\n'
        ),
        mock.patch.object(canergy.rules_doc, "write_docs", _stop),
        mock.patch.object(canergy.bench.run, "run", _stop),
        mock.patch.object(canergy.prove.obligations, "check_all", _stop),
        mock.patch.object(canergy.cli.simulate, "simulate", _stop),
        mock.patch.object(canergy.sim.sweep, "sweep", _stop),
        mock.patch.object(sys, "stdin", io.StringIO(CAPTURE)),
    ]
    with contextlib.ExitStack() as stack:
        for patch in patches:
            stack.enter_context(patch)
        yield


@dataclasses.dataclass(frozen=True)
class Outcome:
    code: int | str
    out: str
    err: str


def _call(name: str, argv: Sequence[str]) -> Outcome:
    """Run the command in this process; its exit status, or ``STARTED``."""
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1)}
    out, err = io.StringIO(), io.StringIO()
    code: int | str
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                if name in EMULATORS:
                    code = EMULATORS[name].main(list(argv))
                else:
                    code = canergy_main([name, *argv])
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else 0 if exc.code is None else -1
            except _Started:
                code = STARTED
    finally:
        for number, handler in handlers.items():
            signal.signal(number, handler)
    return Outcome(code, out.getvalue(), err.getvalue())


def _tree(root: Path) -> dict[str, str]:
    """Every path under ``root`` with its kind, and a file's content hash."""
    found: dict[str, str] = {}
    for folder, dirs, files in os.walk(root):
        for entry in [*dirs, *files]:
            path = Path(folder, entry)
            mode = path.lstat().st_mode
            if stat.S_ISREG(mode):
                kind = "file " + hashlib.sha256(path.read_bytes()).hexdigest()
            else:
                kind = "dir" if stat.S_ISDIR(mode) else f"other {stat.S_IFMT(mode)}"
            found[str(path.relative_to(root))] = kind
    return found


def _outputs(name: str, argv: Sequence[str], root: Path) -> list[Path]:
    """The declared outputs this invocation names (none when its arguments do not parse)."""
    full = list(argv) if name in EMULATORS else [name, *argv]
    parser = PARSERS[name] if name in EMULATORS else build_parser()
    try:
        with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
            args = parser.parse_args(full)
    except SystemExit:
        return []
    values = [getattr(args, dest) for dest in OUTPUTS.get(name, set())]
    return [Path(os.path.normpath(root / v)) for v in values if v is not None]


def _allowed(path: Path, outputs: list[Path]) -> bool:
    """An output, in one, or the lock file a record's keeper holds beside it."""
    return any(path in (o, lock_path(o)) or o in path.parents for o in outputs)


@contextlib.contextmanager
def _notifiers() -> Iterator[list[can.Notifier]]:
    """Every ``can.Notifier`` made inside; those still running at the end are stopped (so that a
    leak fails this run only, not the tests after it) and yielded as the leaked ones."""
    made: list[can.Notifier] = []
    leaked: list[can.Notifier] = []
    real_init = can.Notifier.__init__

    def init(self: can.Notifier, *args: Any, **kwargs: Any) -> None:
        real_init(self, *args, **kwargs)
        made.append(self)

    try:
        with mock.patch.object(can.Notifier, "__init__", init):
            yield leaked
    finally:
        for notifier in made:
            if any(t.is_alive() for t in notifier._readers if isinstance(t, threading.Thread)):
                leaked.append(notifier)
                notifier.stop(timeout=1)


def check_one(name: str, argv: list[str]) -> None:
    threads = set(threading.enumerate())
    with (
        tempfile.TemporaryDirectory() as tmp,
        contextlib.chdir(tmp),
        _notifiers() as leaked,
        _bounded_commands(),
    ):
        root = Path(tmp).resolve()
        for relative, text in FILES.items():
            (root / relative).parent.mkdir(exist_ok=True)
            (root / relative).write_text(text)
        before = _tree(root)
        outcome = _call(name, argv)
        after = _tree(root)
        outputs = _outputs(name, argv, root)
    shown = f"{name} {argv}: exit {outcome.code}\n{outcome.out[-2000:]}\n{outcome.err[-2000:]}"
    assert "Traceback" not in outcome.out + outcome.err, shown
    assert outcome.code in (0, 1, 2, STARTED), shown
    errors = [line for line in outcome.err.splitlines() if "error:" in line]
    assert len(errors) <= 1, shown
    if outcome.code == 2:
        assert outcome.err.strip(), shown
    deleted = sorted(set(before) - set(after))
    assert not deleted, f"deleted {deleted}: {shown}"
    changed = [p for p in sorted(after) if after[p] != before.get(p)]
    outside = [p for p in changed if not _allowed(root / p, outputs)]
    assert not outside, f"created or changed {outside} (outputs {outputs}): {shown}"
    assert not leaked, f"can.Notifier left running: {shown}"
    for thread in set(threading.enumerate()) - threads:
        thread.join(timeout=2)
        assert not thread.is_alive(), f"thread {thread.name} left running: {shown}"
    assert not can.interfaces.virtual.channels, f"virtual bus left open: {shown}"


def test_the_fuzzed_commands_are_the_parsers_own() -> None:
    names = set(PARSERS)
    assert {"demo", "check", "supervisor", "audit", "decode", FIRMWARE} <= names
    for name, dests in OUTPUTS.items():
        assert dests <= {a.dest for a in _fuzzed(PARSERS[name])}, name
    for name, parser in PARSERS.items():
        for action in _fuzzed(parser):
            positional = action.dest in ("file", "channel_filters")  # dump's CHANNEL,FILTER
            assert action.option_strings or positional, (name, action.dest)
            if action.nargs != 0:  # a new kind of value needs a word it accepts in NUMBERS
                assert _valid(action), (name, action.dest)


@pytest.mark.parametrize("name", sorted(PARSERS))
def test_any_arguments_end_cleanly(name: str) -> None:
    @settings(
        max_examples=MORE_EXAMPLES.get(name, EXAMPLES),
        derandomize=True,
        database=None,
        deadline=None,
        phases=[Phase.generate],  # a failure is reported as drawn, at once: no slow shrinking
        suppress_health_check=[HealthCheck.too_slow],
    )
    @given(invocations(name))
    def run(argv: list[str]) -> None:
        check_one(name, argv)

    run()


@pytest.mark.parametrize(
    ("name", "argv"),
    [
        ("audit", ["typo.db"]),
        ("decode", ["sub"]),
        (FIRMWARE, ["--node=1", "--nv=missing/x.nv", "-i", "virtual"]),
        (FIRMWARE, ["--node=1", "--nv=new.json", "--status-file=./new.json", "-i", "virtual"]),
        (FIRMWARE, ["--node=1", "--nv=new.json", "--power-profile=bad.csv", "-i", "virtual"]),
        ("supervisor", ["--nodes=1", "--state=new.json", "--control=new.log", "-i", "virtual"]),
        ("check", ["--units=99999999999999999999"]),
        ("sweep", ["--processes=99999999999", "--out=out"]),
        ("bench", ["--json=missing/x.json"]),
        # found by the fuzzing: a --eds that could not be loaded left the CANopen Notifier running
        ("supervisor", ["--nodes=1", "-i", "virtual", "--state=new.json", "--canopen", "--eds=x"]),
    ],
)
def test_the_harness_sees_these(name: str, argv: list[str]) -> None:
    """Cases from issue 13 (and one the fuzzing found), through the fuzz test's own check."""
    check_one(name, argv)


def test_the_harness_catches_a_stray_file() -> None:
    """The check itself can fail: a command that writes beside its outputs is caught."""

    def litter(args: argparse.Namespace) -> int:
        Path("stray.txt").write_text("x")
        return 0

    with (
        mock.patch("canergy.cli.rules.run", litter),
        pytest.raises(AssertionError, match=r"stray\.txt"),
    ):
        check_one("rules", [])


def test_the_harness_catches_a_traceback() -> None:
    def crash(args: argparse.Namespace) -> int:
        raise OverflowError("too big")

    with (
        mock.patch("canergy.cli.rules.run", crash),
        pytest.raises(OverflowError),
    ):
        check_one("rules", [])
