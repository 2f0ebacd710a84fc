"""The README's and the documentation site's pages, and their python blocks as the tests run
them.

``pages()`` is every page whose blocks run as tests: README.md and the markdown pages of
``docs/`` (the site), README first. A python block preceded by a ``<!-- vcan0: ... -->`` line
needs vcan0: the vcan suite runs it (tests/test_vcan_cia402.py), the normal suite the others
(tests/test_readme.py).
"""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
VCAN_MARK = "<!-- vcan0:"
"""Marks a python block that needs vcan0: the vcan suite runs it."""


def pages() -> list[Path]:
    """README.md, then every markdown page of the site (docs/, its build output excepted)."""
    site = sorted(p for p in DOCS.rglob("*.md") if not {"_build", "_ext"} & set(p.parts))
    return [README, *site]


def page_name(path: Path) -> str:
    """How a page is named in a failure: its path in the repository."""
    return str(path.relative_to(ROOT))


def python_blocks() -> list[tuple[bool, str]]:
    """Every python block of the pages, and whether it is marked ``<!-- vcan0: ...`` (it needs
    vcan0: the vcan suite runs it)."""
    found = []
    for page in pages():
        blocks = re.findall(r"(<!-- vcan0:[^\n]*\n)?```python\n(.*?)```", page.read_text(), re.S)
        found += [(bool(mark), block) for mark, block in blocks]
    return found


def python_blocks_of(page: Path) -> list[str]:
    """The python blocks of one page, in order (e.g. docs/testing.md's, run with pytester)."""
    return re.findall(r"```python\n(.*?)```", page.read_text(), re.S)
