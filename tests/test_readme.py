"""The README's library example runs as printed."""

import re
from pathlib import Path


def test_readme_python_example_runs() -> None:
    text = (Path(__file__).parent.parent / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert blocks, "README lost its python example"
    for block in blocks:
        exec(compile(block, "README.md", "exec"), {})
