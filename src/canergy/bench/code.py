"""Which code a benchmark ran: canergy's version and, run from a git checkout, its commit (with
``+dirty`` when the tree has changes), so that a figure can be traced to what measured it."""

from __future__ import annotations

import subprocess
from pathlib import Path

import canergy


def commit(where: Path | None = None) -> str | None:
    """The short commit of the checkout holding ``where`` (default: this package), ``+dirty``
    when its tracked files differ from it (``+status-unknown`` when git cannot tell); None
    outside a checkout or without git."""
    folder = where or Path(canergy.__file__).resolve().parent

    def git(*args: str) -> str | None:
        try:
            run = subprocess.run(
                ["git", "-C", str(folder), *args], capture_output=True, text=True, timeout=10
            )
        except (OSError, subprocess.SubprocessError):
            return None
        return run.stdout.strip() if run.returncode == 0 else None

    head = git("rev-parse", "--short", "HEAD")
    if not head:
        return None
    changed = git("status", "--porcelain", "--untracked-files=no")
    if changed is None:  # unknown is not clean
        return head + "+status-unknown"
    return head + ("+dirty" if changed else "")


def code() -> dict[str, str | None]:
    """canergy's version and commit, as the bench's results record them."""
    return {"version": canergy.__version__, "commit": commit()}


def line(c: dict[str, str | None]) -> str:
    """The code in one line: ``canergy 0.1.0, commit 1a2b3c4`` (or ``not a git checkout``)."""
    where = f"commit {c['commit']}" if c.get("commit") else "not a git checkout"
    return f"canergy {c['version']}, {where}"
