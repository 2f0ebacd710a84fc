"""Each command is imported only when it runs: ``canergy dbc`` loads no bus, no live stack and
no C extension, and one command whose import is broken leaves the others working."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

HEAVY = ("canergy.live", "canergy.ccore", "canergy.check", "canergy.prove", "can")
"""Packages a command that neither opens a bus nor checks nor proves has no use for."""

LOADED = """
import json, sys
from canergy.cli import main
try:
    code = main(sys.argv[1:])
except SystemExit as exc:
    code = exc.code
print(json.dumps({"code": code, "modules": sorted(sys.modules)}), file=sys.stderr)
"""

BROKEN = """
import sys

class Broken:  # canergy.cli.<BROKEN> fails to import, as a bad edit or a half install would
    @staticmethod
    def find_spec(name, path=None, target=None):
        if name == "canergy.cli." + BROKEN:
            raise ImportError(f"{name} is broken (test)", name=name)
        return None

sys.meta_path.insert(0, Broken)
from canergy.cli import main
sys.exit(main(sys.argv[1:]))
"""


def loaded(*argv: str) -> tuple[int, list[str]]:
    done = subprocess.run(
        [sys.executable, "-c", LOADED, *argv], capture_output=True, text=True, timeout=120
    )
    last = json.loads(done.stderr.strip().splitlines()[-1])
    return int(last["code"] or 0), last["modules"]


def heavy(modules: list[str]) -> list[str]:
    return [m for m in modules if any(m == h or m.startswith(h + ".") for h in HEAVY)]


@pytest.mark.parametrize("argv", [["--help"], ["dbc", "--help"], ["keys", "--help"]])
def test_a_light_command_imports_no_bus_live_stack_or_c_extension(argv: list[str]) -> None:
    code, modules = loaded(*argv)
    assert code == 0
    assert heavy(modules) == []


def test_a_command_that_opens_a_bus_imports_what_it_needs() -> None:
    """The check above can fail: ``supervisor --help`` does load the live stack."""
    code, modules = loaded("supervisor", "--help")
    assert code == 0
    assert "canergy.live.runtime" in heavy(modules)


def test_a_broken_command_touches_no_other(tmp_path: Path) -> None:
    def run(*argv: str) -> subprocess.CompletedProcess[str]:
        code = f"BROKEN = 'supervisor'\n{BROKEN}"
        return subprocess.run(
            [sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=120
        )

    listing = run("--help")
    assert listing.returncode == 0 and "supervisor" in listing.stdout
    out = tmp_path / "canergy.dbc"
    assert run("dbc", "-o", str(out)).returncode == 0 and "BO_ " in out.read_text()
    broken = run("supervisor", "--help")
    assert broken.returncode != 0 and "canergy.cli.supervisor is broken" in broken.stderr
