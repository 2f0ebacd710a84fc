"""The C programs under firmware/build for the tests that run them as processes: ``built`` runs
``make`` for the target every time (quick when it is up to date), so a binary older than its
sources is rebuilt before a test runs it; ``c_node`` and ``c_gateway`` are module fixtures over
it (import them into a test module by name)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

FIRMWARE = Path(__file__).resolve().parents[2] / "firmware"


def built(target: str) -> Path:
    """``firmware/TARGET`` (``build/canergy-node``), made up to date; a build that fails fails
    the test loudly."""
    build = subprocess.run(
        ["make", "-s", "-C", str(FIRMWARE), target], capture_output=True, text=True, timeout=600
    )
    assert build.returncode == 0, f"make {target} failed:\n{build.stdout}{build.stderr}"
    binary = FIRMWARE / target
    assert os.access(binary, os.X_OK), f"{binary} was not built"
    return binary


@pytest.fixture(scope="module")
def c_node() -> Path:
    return built("build/canergy-node")


@pytest.fixture(scope="module")
def c_gateway() -> Path:
    return built("build/canergy-gateway")


def run_without_bus(binary: Path, tmp: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """The node (node 1) or the gateway (node 1 above, node 2 below) run in ``tmp`` on buses
    that do not exist: what it refuses before it opens one, or (exit 2) the CAN socket."""
    if binary.name == "canergy-gateway":
        bus = ["--nodes", "2", "-c", "nosuchcan0", "--upstream-channel", "nosuchcan1"]
    else:
        bus = ["-i", "socketcan", "-c", "nosuchcan0"]
    argv = [str(binary), "--node", "1", *bus, *args]
    return subprocess.run(argv, capture_output=True, text=True, timeout=10, cwd=tmp)


def refused(run: subprocess.CompletedProcess[str], words: str) -> None:
    """``run`` ended with exit 2 and one line on stderr that says ``words``."""
    assert run.returncode == 2, run.stderr
    assert run.stderr.count("\n") == 1 and words in run.stderr, run.stderr


WARN = ["-std=c99", "-Wall", "-Wextra", "-Wpedantic", "-Wconversion", "-Wshadow", "-Wcast-qual"]
WARN += ["-Wstrict-prototypes", "-Wmissing-prototypes", "-Wundef", "-Werror"]
"""firmware/Makefile's WARN."""
GATEWAY_PORT = ["gateway_report.c", "gateway_storage.c", "args.c", "keyfile.c", "paths.c"]
GATEWAY_PORT += ["socketcan.c", "system.c"]
"""canergy-gateway's files (ports/linux) but main's (canergy_gateway.c) and its two buses'."""


def harness(name: str, directory: Path, port: list[str]) -> Path:
    """``directory/NAME``: tests/support/NAME.c, a main() for the port's files ``port``
    (ports/linux) with harness_can.c, built with the library (room for 127 nodes below) and the
    port's warnings under ASan and UBSan; a build that fails fails the test loudly."""
    support = FIRMWARE.parent / "tests" / "support"
    sources = [str(support / f"{name}.c"), str(support / "harness_can.c")]
    sources += [str(FIRMWARE / "ports/linux" / file) for file in port]
    sources += sorted(str(p) for p in (FIRMWARE / "src").glob("*.c"))
    include = ["-I", str(FIRMWARE / "include"), "-I", str(FIRMWARE / "ports/linux")]
    asan = ["-g", "-fsanitize=address,undefined", "-fno-sanitize-recover=all"]
    cmd = ["cc", *WARN, "-O1", *asan, "-DCANERGY_SUPERVISOR_NODES=127U", *include, *sources]
    binary = directory / name
    build = subprocess.run([*cmd, "-o", str(binary)], capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stderr
    return binary
