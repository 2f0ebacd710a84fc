"""The extras: ``canergy[plot]`` (matplotlib), ``canergy[zenoh]`` (eclipse-zenoh), ``canergy[all]``.

A plain ``pip install canergy`` leaves both out. A command that needs a missing one says which
in one line on stderr and exits 2 before doing any work; ``-i zenoh`` fails the same way through
the bus-open error. Here the extras are blocked in a subprocess of this environment; the wheel
installed without them is tested in tests/test_packaging.py.
"""

from __future__ import annotations

import subprocess
import tomllib
from pathlib import Path

import pytest
from support.blocked_imports import EXTRAS, RUN_CLI, run_blocked

from canergy.extras import EXTRAS as EXTRA_MODULES
from canergy.extras import MissingExtra, require

ROOT = Path(__file__).resolve().parents[1]
CAPTURE = ROOT / "tests" / "data" / "two-nodes.log"
PLOT = "needs matplotlib: pip install 'canergy[plot]'"
ZENOH = "needs eclipse-zenoh: pip install 'canergy[zenoh]'"
UPSTREAM = ["--upstream-interface", "zenoh", "--upstream-channel", "site", "--state", "gw.json"]


def _requirement_name(text: str) -> str:
    return text.split("[")[0].split(">")[0].split("=")[0].strip()


def test_pip_installs_the_extras_only_when_asked() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    plain = {_requirement_name(r) for r in project["dependencies"]}
    # cffi: the compiled supervisor core's binding (cryptography needs it as well)
    assert plain == {"python-can", "cantools", "canopen", "cryptography", "cffi"}
    optional = project["optional-dependencies"]
    for extra, (_, distribution) in EXTRA_MODULES.items():
        assert [_requirement_name(r) for r in optional[extra]] == [distribution]
    assert optional["all"] == [f"canergy[{','.join(sorted(EXTRA_MODULES))}]"]
    assert "canergy[all]" in optional["dev"]  # ./scripts/test installs everything


def test_the_missing_extra_line() -> None:
    assert str(MissingExtra("plot")) == PLOT
    assert isinstance(MissingExtra("plot"), ImportError)
    gone = ModuleNotFoundError("No module named 'zenoh'", name="zenoh")
    assert str(MissingExtra("zenoh", gone)) == ZENOH
    broken = ModuleNotFoundError("No module named 'numpy'", name="numpy")
    assert str(MissingExtra("plot", broken)) == f"{PLOT} (No module named 'numpy')"


def test_require(monkeypatch: pytest.MonkeyPatch) -> None:
    require("plot")  # this environment has every extra
    require("zenoh")
    monkeypatch.setitem(EXTRA_MODULES, "plot", ("canergy_no_such_module", "matplotlib"))
    with pytest.raises(MissingExtra, match=r"^needs matplotlib: pip install 'canergy\[plot\]'$"):
        require("plot")


def _cli(tmp: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return run_blocked(EXTRAS, RUN_CLI, *args, cwd=tmp)


def _one_line(out: subprocess.CompletedProcess[str]) -> str:
    assert out.returncode == 2 and not out.stdout, out
    (line,) = out.stderr.splitlines()  # no traceback
    return line


@pytest.mark.parametrize(
    "argv",
    [
        ["plot", str(CAPTURE), "-o", "out/figure.png"],
        ["simulate", "--out", "out/sim"],
        ["sweep", "--out", "out/sweep", "--seeds", "1"],
        ["rules", "--docs", "out"],
    ],
    ids=lambda argv: argv[0],
)
def test_a_command_that_draws_says_it_needs_matplotlib(tmp_path: Path, argv: list[str]) -> None:
    (tmp_path / "out").mkdir()
    assert _one_line(_cli(tmp_path, *argv)) == f"canergy {argv[0]}: {PLOT}"
    assert list((tmp_path / "out").iterdir()) == []  # checked before any work


def test_prove_says_it_needs_z3(tmp_path: Path) -> None:
    line = _one_line(_cli(tmp_path, "prove", "--json", "out.json"))
    assert line == "canergy prove: needs z3-solver: pip install 'canergy[prove]'"
    assert not (tmp_path / "out.json").exists()  # checked before any work


def test_rules_without_docs_needs_no_matplotlib(tmp_path: Path) -> None:
    out = _cli(tmp_path, "rules")
    assert out.returncode == 0 and out.stdout.startswith("# Transition tables"), out.stderr


@pytest.mark.parametrize(
    "argv",
    [
        ["supervisor", "-i", "zenoh", "-c", "site", "--nodes", "1", "--state", "s.json"],
        ["grant", "-i", "zenoh", "-c", "site", "--node", "1", "--amount", "1J", "--state", "g"],
        ["dump", "-i", "zenoh", "-c", "site"],
        ["monitor", "-i", "zenoh", "-c", "site", "--once"],
        ["gateway", "--node", "1", "--nodes", "1", "-i", "virtual", "-c", "below", *UPSTREAM],
    ],
    ids=lambda argv: argv[0],
)
def test_the_zenoh_interface_says_it_needs_eclipse_zenoh(tmp_path: Path, argv: list[str]) -> None:
    line = _one_line(_cli(tmp_path, *argv))
    which = "upstream CAN bus" if "--upstream-interface" in argv else "CAN bus"
    assert line.startswith(f"canergy {argv[0]}: error: cannot open the {which}: "), line
    assert line.endswith(f"for CAN interface 'zenoh': {ZENOH}"), line


def test_python_can_reports_the_missing_extra_as_its_interface_error(tmp_path: Path) -> None:
    code = """
import can
try:
    can.Bus(interface="zenoh", channel="site")
except can.CanInterfaceNotImplementedError as exc:
    print(exc)
"""
    out = run_blocked(EXTRAS, code, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout == (
        "Cannot import module canergy.live.transports.zenoh_bus for CAN interface "
        f"'zenoh': {ZENOH}\n"
    )
