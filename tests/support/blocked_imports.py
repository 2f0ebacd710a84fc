"""A ``python -c`` of this environment with some packages unimportable, however imported.

``run_blocked`` stands for a host-only or light install (``pip install canergy``: no emulator, no
extras) without building one: tests/test_packaging.py blocks the emulator and the extras,
tests/test_extras.py the extras; ``RUN_CLI`` runs canergy's command line in that process.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

EXTRAS = ("matplotlib", "mpl_toolkits", "numpy", "zenoh", "z3")
"""What ``canergy[plot]``, ``canergy[zenoh]`` and ``canergy[prove]`` bring that canergy imports
(numpy: matplotlib's, and no dependency of a light install)."""

# Prepended to each ``python -c`` of run_blocked (after BLOCKED = (...)): stands for a host-only
# or light install, where importing a blocked package (or anything under it) fails however it is
# attempted.
BLOCKER = """
import sys

class Blocked:
    @staticmethod
    def find_spec(name, path=None, target=None):
        if name.partition(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r} (blocked)", name=name)
        return None

sys.meta_path.insert(0, Blocked)
for _name in BLOCKED:
    try:
        __import__(_name)
    except ImportError:
        pass
    else:
        sys.exit(f"the blocker let {_name} through")
"""

RUN_CLI = "import runpy; runpy.run_module('canergy', run_name='__main__', alter_sys=True)"


def run_blocked(
    blocked: tuple[str, ...], code: str, *args: str, cwd: Path
) -> subprocess.CompletedProcess[str]:
    """``python -c code args`` in this environment with ``blocked`` packages unimportable."""
    return subprocess.run(
        [sys.executable, "-c", f"BLOCKED = {blocked!r}\n" + BLOCKER + code, *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=120,
    )
