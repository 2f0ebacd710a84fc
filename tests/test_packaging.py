"""canergy without its emulator or its extras, and canergy as its wheel installs it (no source
tree behind it, no extras: ``pip install canergy``).

``firmware_model`` depends on canergy, never the reverse: every canergy module imports while the
emulator cannot be imported, and a wheel carries what the library loads at run time (the EDS).
Without matplotlib and eclipse-zenoh (``canergy[plot]``, ``canergy[zenoh]``) every module still
imports but those ``canergy.extras.NEEDS_EXTRA`` lists, and the commands without a figure or a
Zenoh bus run from a light install; one that needs a missing extra says which in one line.
"""

from __future__ import annotations

import importlib.metadata
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import uuid
import zipfile
from dataclasses import dataclass
from pathlib import Path

import pytest
from support.blocked_imports import EXTRAS, RUN_CLI, run_blocked

ROOT = Path(__file__).resolve().parents[1]
EMULATOR = ("firmware_model",)
LIGHT_SIZE_MAX = 80_000_000
"""Bytes a light install (``pip install canergy``: no extras) may add to a bare venv."""

IMPORT_ALL = """
import importlib, json, pkgutil
import canergy

def fail(name):  # walk_packages swallows a subpackage's ImportError without this
    raise ImportError(f"cannot import {name}")

names = [m.name for m in pkgutil.walk_packages(canergy.__path__, "canergy.", onerror=fail)]
failed = {}
for name in names:
    if not name.endswith(".__main__"):  # canergy.__main__ runs the CLI (next test)
        try:
            importlib.import_module(name)
        except ImportError as exc:
            failed[name] = [type(exc).__name__, str(exc)]
print(json.dumps({"names": names, "failed": failed}))
"""


@pytest.mark.parametrize("extras", [True, False], ids=["with-extras", "without-extras"])
def test_every_canergy_module_imports_without_the_emulator(tmp_path: Path, extras: bool) -> None:
    """Without the extras, exactly the modules ``NEEDS_EXTRA`` lists fail, each with the line
    that names its extra (the commands import them only when they draw or open a Zenoh bus)."""
    from canergy.extras import NEEDS_EXTRA, MissingExtra

    out = run_blocked(EMULATOR if extras else EMULATOR + EXTRAS, IMPORT_ALL, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    names = set(result["names"])
    assert len(names) >= 40
    assert {
        "canergy.cli",
        "canergy.cli.supervisor",
        "canergy.bench.run",
        "canergy.bench.live",
    } <= names
    assert set(NEEDS_EXTRA) <= names
    expected = (
        {}
        if extras
        else {n: ["MissingExtra", str(MissingExtra(e))] for n, e in NEEDS_EXTRA.items()}
    )
    assert result["failed"] == expected


def test_the_cli_runs_without_the_emulator_and_the_extras(tmp_path: Path) -> None:
    out = run_blocked(EMULATOR + EXTRAS, RUN_CLI, "supervisor", "--help", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "--canopen" in out.stdout and "--eds" in out.stdout


def _call(
    argv: list[str], cwd: Path, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(argv, capture_output=True, text=True, cwd=cwd, env=env, timeout=120)


def _run(argv: list[str], cwd: Path, env: dict[str, str] | None = None) -> str:
    out = _call(argv, cwd, env)
    assert out.returncode == 0, f"{argv}:\n{out.stdout}\n{out.stderr}"
    return out.stdout


def _build_wheel(tmp: Path) -> Path:
    """The wheel of a copy of the source tree (building in place would leave build/ behind):
    what the sdist holds (MANIFEST.in), the C sources of the compiled core included, and no
    extension built here before (the wheel's is its own)."""
    tree = tmp / "tree"
    skip = shutil.ignore_patterns("__pycache__", "*.egg-info", "*.so")
    shutil.copytree(ROOT / "src", tree / "src", ignore=skip)
    shutil.copytree(ROOT / "firmware_model", tree / "firmware_model", ignore=skip)
    for part in ("src", "include"):
        shutil.copytree(ROOT / "firmware" / part, tree / "firmware" / part, ignore=skip)
    shutil.copy2(ROOT / "firmware" / "Makefile", tree / "firmware" / "Makefile")  # its SRCS
    for name in ("pyproject.toml", "setup.py", "MANIFEST.in", "README.md", "LICENSE"):
        shutil.copy2(ROOT / name, tree / name)
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "--no-input"]
    build = ["wheel", "--no-deps", "--no-build-isolation", "--no-index", "-w", str(tmp / "dist")]
    _run([*pip, *build, str(tree)], tmp)
    (wheel,) = (tmp / "dist").glob("canergy-*.whl")
    return wheel


def _site_packages(venv: Path) -> Path:
    return venv / "lib" / f"python{sys.version_info[0]}.{sys.version_info[1]}" / "site-packages"


def _size(tree: Path) -> int:
    """Bytes of the files under ``tree`` (as installed: sources, bytecode, libraries)."""
    return sum(p.lstat().st_size for p in tree.rglob("*") if p.is_file() and not p.is_symlink())


def _venv(path: Path) -> Path:
    _run([sys.executable, "-m", "venv", "--without-pip", str(path)], path.parent)
    return path / "bin" / "python"


def _host_install(tmp: Path, wheel: Path) -> tuple[Path, int, float]:
    """A fresh venv holding the wheel and its dependencies, no extra (``pip install canergy``
    from the package index pip is set up with, each dependency at this environment's version),
    less firmware_model. Returns its python, the bytes it adds to a bare venv and the seconds
    pip took."""
    python = _venv(tmp / "venv")
    bare = _size(_site_packages(_venv(tmp / "bare")))
    pins = tmp / "constraints.txt"  # the versions the rest of the suite tests
    versions = {d.metadata["Name"]: d.version for d in importlib.metadata.distributions()}
    versions.pop("canergy", None)  # the wheel's, not the editable install's
    pins.write_text("".join(f"{name}=={v}\n" for name, v in versions.items() if name))
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "--no-input"]
    start = time.monotonic()
    _run([*pip, "--python", str(python), "install", "-q", "-c", str(pins), str(wheel)], tmp)
    seconds = time.monotonic() - start
    site = _site_packages(tmp / "venv")
    added = _size(site) - bare  # as pip installs it, the emulator included
    shutil.rmtree(site / "firmware_model")  # the wheel ships the emulator; a host goes without
    return python, added, seconds


PROBE = """
import json
import canopen
import canergy
from canergy.live.canopen.shared_bus import EDS
try:
    import firmware_model
    emulator = firmware_model.__file__
except ImportError:
    emulator = None
od = canopen.import_od(str(EDS))
print(json.dumps({"canergy": canergy.__file__, "eds": str(EDS), "emulator": emulator,
                  "objects": {o.index: o.name for o in od.values()}}))
"""


@dataclass(frozen=True)
class Install:
    wheel: Path
    venv: Path
    env: dict[str, str]
    cwd: Path
    size: int
    """Bytes the install added to a bare venv."""
    seconds: float
    """What pip took to install it."""

    def call(self, command: str, *args: str) -> subprocess.CompletedProcess[str]:
        """``command`` from the venv's bin/ (python, canergy), whatever its exit status."""
        return _call([str(self.venv / "bin" / command), *args], self.cwd, self.env)

    def run(self, command: str, *args: str) -> str:
        """``command`` from the venv's bin/ (python, canergy), which must exit 0; its stdout."""
        return _run([str(self.venv / "bin" / command), *args], self.cwd, self.env)


@pytest.fixture(scope="module")
def host(tmp_path_factory: pytest.TempPathFactory) -> Install:
    tmp = tmp_path_factory.mktemp("wheel")
    wheel = _build_wheel(tmp)
    python, size, seconds = _host_install(tmp, wheel)
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}
    return Install(wheel, python.parents[1], env, tmp, size, seconds)


def test_the_wheel_carries_every_module_and_the_eds(host: Install) -> None:
    names = set(zipfile.ZipFile(host.wheel).namelist())
    eds = "canergy/live/canopen/canergy_node.eds"
    assert {eds, "canergy/py.typed"} <= names
    assert zipfile.ZipFile(host.wheel).read(eds) == (ROOT / "src" / eds).read_bytes()
    sources = {p.relative_to(ROOT / "src").as_posix() for p in (ROOT / "src").rglob("*.py")}
    assert sources <= names, f"missing from the wheel: {sorted(sources - names)}"


def test_the_installed_canergy_is_the_wheel_and_reads_its_eds(host: Install) -> None:
    probe = json.loads(host.run("python", "-c", PROBE))
    assert Path(probe["canergy"]).is_relative_to(host.venv), probe  # the wheel, not src/
    assert Path(probe["eds"]).is_relative_to(host.venv) and probe["emulator"] is None
    assert {int(i) for i in probe["objects"]} >= {*range(0x2000, 0x2008), 0x2100, 0x2101, 0x2102}
    assert probe["objects"][str(0x2000)] == "Usable budget uJ"


def test_the_installed_demo_runs(host: Install) -> None:
    demo = host.run("canergy", "demo", "--nodes", "2", "--transactions", "20", "--json")
    assert json.loads(demo)["passive"] is True


@pytest.mark.parametrize("canopen", [False, True], ids=["plain", "canopen"])
def test_the_installed_supervisor_runs(host: Install, canopen: bool) -> None:
    """On python-can's virtual bus, briefly; its CANopen side loads the packaged EDS (a missing
    EDS exits 2 at once)."""
    argv = [str(host.venv / "bin" / "canergy"), "supervisor", "--nodes", "1"]
    argv += ["-i", "virtual", "-c", uuid.uuid4().hex, "--status-period", "0.2"]
    argv += ["--state", str(host.cwd / f"state-{canopen}.json"), "--no-fsync"]
    if canopen:
        argv += ["--canopen", "--heartbeat-timeout", "0.5"]
    proc = subprocess.Popen(
        argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=host.cwd, env=host.env
    )
    watchdog = threading.Timer(60, proc.kill)
    watchdog.start()
    try:
        assert proc.stdout is not None
        status = json.loads(proc.stdout.readline() or "null")
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        watchdog.cancel()
        proc.kill()
    assert proc.returncode == 0, err
    assert status is not None and status["nodes"]["1"]["lost"] is True  # no node answers
    assert status["core"] == "c"  # the wheel carries the compiled core: --core auto takes it


def test_the_installed_bench_skips_the_emulator_part_in_one_line(host: Install) -> None:
    report = host.cwd / "bench.json"
    out = subprocess.run(
        [str(host.venv / "bin" / "canergy"), "bench", "--quick", "--json", str(report)],
        capture_output=True,
        text=True,
        cwd=host.cwd,
        env=host.env,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    (line,) = out.stderr.splitlines()  # no traceback
    assert line.startswith("canergy bench: skipped the live stack") and "firmware_model" in line
    result = json.loads(report.read_text())
    assert result["live"] == [] and result["skipped"] == [line.removeprefix("canergy bench: ")]
    assert "client_nv_record_bytes" not in result["memory"]
    assert result["sdo"]["writes"] > 0 and result["codec"]["rows"]  # these need no emulator


# Run by the light install's python: ``canergy dump`` on a virtual channel (in this process: the
# virtual bus does not cross processes) while frames of a capture are sent on it.
DUMP = """
import sys, threading, time
from pathlib import Path
import can
from can.interfaces.virtual import channels
from canergy.cli import main
from canergy.inspect.captures import read_file

capture, channel = sys.argv[1:]
frames = list(read_file(Path(capture), lambda *a: None))[:3]
result = []
argv = ["dump", "-i", "virtual", "-c", channel, "-n", str(len(frames)), "--json"]
thread = threading.Thread(target=lambda: result.append(main(argv)), daemon=True)
thread.start()
with can.Bus(interface="virtual", channel=channel) as bus:
    deadline = time.monotonic() + 30
    while len(channels.get(channel, [])) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)  # until dump has opened its end of the channel
    for frame in frames:
        bus.send(frame)
    thread.join(timeout=30)
sys.exit(result[0] if result else "dump did not end")
"""


def _one_line(out: subprocess.CompletedProcess[str]) -> str:
    """The single stderr line of a command that exited 2 (no traceback, nothing on stdout)."""
    assert out.returncode == 2 and not out.stdout, out
    (line,) = out.stderr.splitlines()
    return line


@pytest.fixture(scope="module")
def capture(host: Install) -> Path:
    """A demo's capture, written by the light install."""
    log = host.cwd / "demo.log"
    host.run("canergy", "demo", "--nodes", "2", "--transactions", "20", "--log", str(log))
    return log


def test_the_light_install_is_small_and_has_no_extra(
    host: Install, request: pytest.FixtureRequest
) -> None:
    """``pip install canergy`` adds under LIGHT_SIZE_MAX bytes (about 27 MB; with ``[all]``
    some 230 MB: matplotlib, numpy, eclipse-zenoh), none of it an extra's."""
    request.node.user_properties += [
        ("light_install_bytes", host.size),
        ("light_install_pip_seconds", round(host.seconds, 1)),
    ]
    assert host.size < LIGHT_SIZE_MAX, f"{host.size:,} bytes"
    code = "import importlib.util as u, sys; print(*[bool(u.find_spec(m)) for m in sys.argv[1:]])"
    assert host.run("python", "-c", code, *EXTRAS).split() == ["False"] * len(EXTRAS)


def test_the_installed_grant_runs(host: Install) -> None:
    """A single run on the virtual bus: no node answers, so nothing is granted (exit 1), and
    being alone on python-can's virtual bus, it says why nothing could be heard."""
    state = host.cwd / "grant.json"
    argv = ["grant", "-i", "virtual", "-c", uuid.uuid4().hex, "--node", "1", "--amount", "1J"]
    argv += ["--initial", "5J", "--state", str(state), "--no-fsync", "--timeout", "0.5s"]
    out = host.call("canergy", *argv)
    assert out.returncode == 1, out
    first, rest = out.stderr.split("\n", 1)
    assert first.startswith("canergy grant: warning: --no-fsync: records are not synced"), out
    assert rest.startswith("canergy: nothing can be heard on python-can's virtual bus"), out
    assert json.loads(out.stdout) == {
        "error": "node never heard from (or still joining): nothing granted",
        "node": 1,
    }
    assert json.loads(state.read_text())["usable_uj"] == 5_000_000


def test_the_installed_dump_decode_and_audit_run(host: Install, capture: Path) -> None:
    dumped = host.run("python", "-c", DUMP, str(capture), uuid.uuid4().hex)
    lines = [json.loads(x) for x in dumped.splitlines()]
    assert len(lines) == 3 and all(x["crc_ok"] and x["type"] for x in lines), lines
    decoded = host.run("canergy", "decode", str(capture), "--json").splitlines()
    fields = [(x["id"], x["data"], x["type"]) for x in lines]
    assert [(x["id"], x["data"], x["type"]) for x in map(json.loads, decoded[:3])] == fields
    audit = json.loads(host.run("canergy", "audit", str(capture), "--reordered", "--json"))
    assert (
        audit["passive"] is True and not audit["violations"] and set(audit["nodes"]) == {"1", "2"}
    )


def test_the_installed_check_runs(host: Install) -> None:
    argv = ["check", "--clients", "2", "--transactions", "1", "--losses", "1", "--json"]
    result = json.loads(host.run("canergy", *argv))
    assert result["complete"] is True and result["violations"] == 0 and result["states"] > 100


def test_the_installed_plot_says_in_one_line_that_it_needs_matplotlib(
    host: Install, capture: Path
) -> None:
    figure = host.cwd / "figure.png"
    out = host.call("canergy", "plot", str(capture), "-o", str(figure))
    assert _one_line(out) == "canergy plot: needs matplotlib: pip install 'canergy[plot]'"
    assert not figure.exists()


def test_the_installed_zenoh_interface_says_in_one_line_that_it_needs_eclipse_zenoh(
    host: Install,
) -> None:
    """python-can finds canergy's interface by its entry point and fails to import it."""
    argv = ["supervisor", "-i", "zenoh", "-c", "site", "--nodes", "1"]
    out = host.call("canergy", *argv, "--state", str(host.cwd / "zenoh.json"))
    line = _one_line(out)
    assert line.startswith("canergy supervisor: error: cannot open the CAN bus: ")
    assert line.endswith(": needs eclipse-zenoh: pip install 'canergy[zenoh]'")
