"""canergy without its emulator, and canergy as its wheel installs it (no source tree behind it).

``firmware_model`` depends on canergy, never the reverse: every canergy module imports while the
emulator cannot be imported, and a wheel carries what the library loads at run time (the EDS).
"""

from __future__ import annotations

import importlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import uuid
import zipfile
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DEPENDENCIES = ("can", "canopen", "cantools", "matplotlib")

# Prepended to each ``python -c`` below: stands for a host-only install, where importing
# firmware_model (or anything under it) fails however it is attempted.
NO_EMULATOR = """
import sys

class NoEmulator:
    @staticmethod
    def find_spec(name, path=None, target=None):
        if name.partition(".")[0] == "firmware_model":
            raise ModuleNotFoundError(f"No module named {name!r} (blocked)", name=name)
        return None

sys.meta_path.insert(0, NoEmulator)
try:
    import firmware_model
except ImportError:
    pass
else:
    sys.exit("the blocker let firmware_model through")
"""

RUN_CLI = "import runpy; runpy.run_module('canergy', run_name='__main__', alter_sys=True)"


def _without_emulator(code: str, *args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", NO_EMULATOR + code, *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=120,
    )


def test_every_canergy_module_imports_without_the_emulator(tmp_path: Path) -> None:
    code = """
import importlib, pkgutil
import canergy

def fail(name):  # walk_packages swallows a subpackage's ImportError without this
    raise ImportError(f"cannot import {name}")

names = [m.name for m in pkgutil.walk_packages(canergy.__path__, "canergy.", onerror=fail)]
for name in names:
    if not name.endswith(".__main__"):  # canergy.__main__ runs the CLI (next test)
        importlib.import_module(name)
print(len(names), " ".join(names))
"""
    out = _without_emulator(code, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    count, names = out.stdout.split(maxsplit=1)
    assert int(count) >= 40
    assert {"canergy.cli", "canergy.cli_live", "canergy.bench.run", "canergy.bench.live"} <= set(
        names.split()
    )


def test_the_cli_runs_without_the_emulator(tmp_path: Path) -> None:
    out = _without_emulator(RUN_CLI, "supervisor", "--help", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "--canopen" in out.stdout and "--eds" in out.stdout


def _run(argv: list[str], cwd: Path, env: dict[str, str] | None = None) -> str:
    out = subprocess.run(argv, capture_output=True, text=True, cwd=cwd, env=env, timeout=120)
    assert out.returncode == 0, f"{argv}:\n{out.stdout}\n{out.stderr}"
    return out.stdout


def _build_wheel(tmp: Path) -> Path:
    """The wheel of a copy of the source tree (building in place would leave build/ behind)."""
    tree = tmp / "tree"
    skip = shutil.ignore_patterns("__pycache__", "*.egg-info")
    shutil.copytree(ROOT / "src", tree / "src", ignore=skip)
    shutil.copytree(ROOT / "firmware_model", tree / "firmware_model", ignore=skip)
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(ROOT / name, tree / name)
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "--no-input"]
    build = ["wheel", "--no-deps", "--no-build-isolation", "--no-index", "-w", str(tmp / "dist")]
    _run([*pip, *build, str(tree)], tmp)
    (wheel,) = (tmp / "dist").glob("canergy-*.whl")
    return wheel


def _host_install(tmp: Path, wheel: Path) -> Path:
    """A fresh venv holding the wheel less firmware_model; the dependencies come from this
    environment's site-packages through a path file (which runs none of that directory's own
    path files, so no editable finder leads back to the source tree). Returns its python."""
    venv = tmp / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], tmp)
    python = venv / "bin" / "python"
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "--no-input"]
    _run([*pip, "--python", str(python), "install", "--no-deps", "--no-index", str(wheel)], tmp)
    site = venv / "lib" / f"python{sys.version_info[0]}.{sys.version_info[1]}" / "site-packages"
    shutil.rmtree(site / "firmware_model")  # the wheel ships the emulator; a host goes without
    deps = {str(Path(importlib.import_module(m).__file__ or "").parents[1]) for m in DEPENDENCIES}
    (site / "dependencies.pth").write_text("".join(f"{d}\n" for d in sorted(deps)))
    return python


PROBE = """
import json
import canopen
import canergy
from canergy.live.shared_bus import EDS
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

    def run(self, command: str, *args: str) -> str:
        """``command`` from the venv's bin/ (python, canergy), which must exit 0; its stdout."""
        return _run([str(self.venv / "bin" / command), *args], self.cwd, self.env)


@pytest.fixture(scope="module")
def host(tmp_path_factory: pytest.TempPathFactory) -> Install:
    tmp = tmp_path_factory.mktemp("wheel")
    wheel = _build_wheel(tmp)
    python = _host_install(tmp, wheel)
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}
    return Install(wheel, python.parents[1], env, tmp)


def test_the_wheel_carries_every_module_and_the_eds(host: Install) -> None:
    names = set(zipfile.ZipFile(host.wheel).namelist())
    eds = "canergy/live/canergy_node.eds"
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


def test_the_installed_supervisor_runs_with_canopen(host: Install) -> None:
    """Its CANopen side loads the packaged EDS (a missing EDS exits 2 at once)."""
    argv = [str(host.venv / "bin" / "canergy"), "supervisor", "--nodes", "1", "--canopen"]
    argv += ["-i", "virtual", "-c", uuid.uuid4().hex, "--status-period", "0.2"]
    argv += ["--state", str(host.cwd / "state.json"), "--no-fsync", "--heartbeat-timeout", "0.5"]
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
