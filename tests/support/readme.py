"""The README's python blocks, as the tests run them.

A block preceded by a ``<!-- vcan0: ... -->`` line needs vcan0: the vcan suite runs it
(tests/test_vcan_cia402.py), the normal suite the others (tests/test_readme.py).
"""

import re
from pathlib import Path

README = Path(__file__).resolve().parents[2] / "README.md"
VCAN_MARK = "<!-- vcan0:"
"""Marks a python block that needs vcan0: the vcan suite runs it."""


def python_blocks() -> list[tuple[bool, str]]:
    """Every python block of the README, and whether it is marked ``<!-- vcan0: ...`` (it needs
    vcan0: the vcan suite runs it)."""
    text = README.read_text()
    found = re.findall(r"(<!-- vcan0:[^\n]*\n)?```python\n(.*?)```", text, re.S)
    return [(bool(mark), block) for mark, block in found]
