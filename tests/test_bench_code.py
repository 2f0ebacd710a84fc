"""The bench names the code it measured: canergy's version and the checkout's commit, marked
dirty when tracked files changed; nothing outside a checkout."""

from __future__ import annotations

import subprocess
from pathlib import Path

import canergy
from canergy.bench.code import code, commit, line


def _git(repo: Path, *args: str) -> str:
    run = subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    return run.stdout.strip()


def test_a_checkout_is_named_by_its_commit_and_marked_dirty_when_changed(tmp_path: Path) -> None:
    _git(tmp_path, "init", "-q")
    (tmp_path / "f.txt").write_text("one\n")
    _git(tmp_path, "add", "f.txt")
    _git(tmp_path, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "one")
    head = _git(tmp_path, "rev-parse", "--short", "HEAD")
    assert commit(tmp_path) == head
    (tmp_path / "new.txt").write_text("untracked files change no figure\n")
    assert commit(tmp_path) == head
    (tmp_path / "f.txt").write_text("two\n")
    assert commit(tmp_path) == f"{head}+dirty"
    (tmp_path / ".git" / "index").write_bytes(b"not an index")  # git status now fails
    assert commit(tmp_path) == f"{head}+status-unknown"
    assert (
        line({"version": "9.9", "commit": f"{head}+dirty"}) == f"canergy 9.9, commit {head}+dirty"
    )


def test_outside_a_checkout_there_is_no_commit(tmp_path: Path) -> None:
    assert commit(tmp_path) is None
    assert line({"version": "9.9", "commit": None}) == "canergy 9.9, not a git checkout"


def test_the_results_carry_this_package_version() -> None:
    assert code()["version"] == canergy.__version__
