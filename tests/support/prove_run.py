"""``canergy prove`` run as a user runs it, its JSON report read back."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from canergy.cli import main


def prove(tmp_path: Path, *args: str) -> tuple[int, list[dict[str, Any]]]:
    """``canergy prove -q --json`` with ``args``: its exit code and every obligation's result."""
    out = tmp_path / "prove.json"
    code = main(["prove", "-q", "--json", str(out), *args])
    return code, json.loads(out.read_text())
