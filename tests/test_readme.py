"""The README's library example runs as printed."""

import re
import shlex
from pathlib import Path


def test_readme_python_example_runs() -> None:
    text = (Path(__file__).parent.parent / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert blocks, "README lost its python example"
    for block in blocks:
        exec(compile(block, "README.md", "exec"), {})


def _shell_commands(prefix: str) -> list[list[str]]:
    text = (Path(__file__).parent.parent / "README.md").read_text()
    commands = []
    for block in re.findall(r"```sh\n(.*?)```", text, re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split("#")[0].strip()
            if line.startswith(prefix):
                commands.append(shlex.split(line)[len(prefix.split()) :])
    return commands


def test_readme_bench_commands_parse() -> None:
    from canergy.cli import build_parser
    from firmware_model.__main__ import build_parser as firmware_parser

    canergy = _shell_commands("canergy ")
    firmware = _shell_commands("python -m firmware_model")
    assert len(canergy) >= 4 and firmware
    for argv in canergy:
        build_parser().parse_args(argv)  # exits 2 on a flag that does not exist
    for argv in firmware:
        firmware_parser().parse_args(argv)
