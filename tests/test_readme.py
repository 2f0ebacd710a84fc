"""The README's library example runs as printed."""

import re
import shlex
from pathlib import Path

from support.readme import python_blocks


def test_readme_python_example_runs() -> None:
    blocks = [block for on_vcan, block in python_blocks() if not on_vcan]
    assert blocks, "README lost its python example"
    for block in blocks:
        exec(compile(block, "README.md", "exec"), {})


def _shell_commands(prefix: str) -> list[list[str]]:
    text = (Path(__file__).parent.parent / "README.md").read_text()
    commands = []
    for block in re.findall(r"```sh\n(.*?)```", text, re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = re.split(r"\s(?:#|\||>|&&|;)", f" {line}")[0].strip().removesuffix("&")
            if line.startswith(prefix):
                commands.append(shlex.split(line)[len(prefix.split()) :])
    return commands


def test_readme_bench_commands_parse() -> None:
    from canergy.cli import build_parser
    from firmware_model.__main__ import build_parser as firmware_parser
    from firmware_model.drive.__main__ import build_parser as drive_parser

    canergy = _shell_commands("canergy ")
    firmware = _shell_commands("python -m firmware_model ")
    drive = _shell_commands("python -m firmware_model.drive ")
    assert len(canergy) >= 4 and firmware and drive
    for argv in canergy:
        build_parser().parse_args(argv)  # exits 2 on a flag that does not exist
    for argv in firmware:
        firmware_parser().parse_args(argv)
    for argv in drive:
        drive_parser().parse_args(argv)


def test_readme_grants_ask_what_their_supervisor_allows() -> None:
    """Each README grant fits the limits of the supervisor that serves it (a `grant --control`
    goes to the README's supervisor with that socket; a single-run grant is its own)."""
    from canergy.cli import build_parser

    parsed = [build_parser().parse_args(argv) for argv in _shell_commands("canergy ")]
    serving = ("supervisor", "gateway")
    served_by = {a.control: a for a in parsed if a.command in serving and a.control}
    grants = [a for a in parsed if a.command == "grant"]
    assert any(g.control for g in grants) and any(not g.control for g in grants)
    for grant in grants:
        sup = served_by[grant.control] if grant.control else grant
        caps = [sup.max_grant] + ([sup.max_total] if sup.max_total else [])
        caps += [sup.initial] if sup.command != "gateway" else []  # a gateway's comes from above
        assert grant.amount <= min(caps), f"--amount {grant.amount} µJ is above {min(caps)} µJ"
