"""The library examples of the README and the site's pages run as printed; their shell commands
parse."""

import re
import shlex
from pathlib import Path

from support.readme import pages, python_blocks


def test_readme_python_example_runs() -> None:
    blocks = [block for on_vcan, block in python_blocks() if not on_vcan]
    assert blocks, "README lost its python example"
    for block in blocks:
        exec(compile(block, "README.md", "exec"), {})


def _shell_commands(prefix: str) -> list[list[str]]:
    text = "\n".join(page.read_text() for page in pages())
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


def _heading_anchors(page: Path) -> set[str]:
    """The anchors GitHub (and the site, myst_heading_anchors) give a page's headings."""
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    found = set()
    for heading in re.findall(r"^#+ (.*)$", text, flags=re.M):
        words = re.sub(r"[^\w\- ]", "", re.sub(r"[`*]", "", heading.strip()).lower())
        found.add(words.replace(" ", "-"))
    return found


def test_readme_links_reach_pages_and_headings_that_exist() -> None:
    """The README is not part of the site, whose build checks its own links: its links into the
    site and the repository are checked here."""
    readme = pages()[0]
    broken = []
    for link in re.findall(r"\]\(([^)\s]+)\)", readme.read_text()):
        if re.match(r"[a-z]+:", link):
            continue
        path, _, anchor = link.partition("#")
        target = readme.parent / path if path else readme
        if not target.exists() or (
            anchor and target.suffix == ".md" and anchor not in _heading_anchors(target)
        ):
            broken.append(link)
    assert not broken
