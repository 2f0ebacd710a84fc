"""Sphinx configuration of canergy's documentation site (built by scripts/docs)."""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE / "_ext"), str(HERE.parent / "src"), str(HERE.parent)]

from canergy import __version__  # noqa: E402

project = "canergy"
author = "canergy contributors"
copyright = "canergy contributors, MIT licence"
release = version = __version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "cli_reference",
]
source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "_ext", "Thumbs.db", ".DS_Store"]

smartquotes = False
"""`--flag` stays two hyphens and quotes stay straight: text is meant to be copied."""
myst_enable_extensions = ["deflist", "colon_fence"]
myst_heading_anchors = 4
"""Headings get GitHub's anchors, so `page.md#a-heading` links work on GitHub and here."""

html_theme = "furo"
html_title = f"canergy {release}"

autodoc_member_order = "bysource"
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_typehints = "description"
"""Type hints shown with the parameters (the docstrings are prose, not Google or NumPy style)."""
autodoc_typehints_format = "short"

nitpicky = True
nitpick_ignore_regex = [
    # third-party and standard-library types: no intersphinx (the build reaches no network)
    ("py:.*", r"(can|canopen|cryptography|z3|numpy|matplotlib|cffi|hypothesis)\..*"),
    ("py:.*", r"(collections\.abc|typing|enum|pathlib|argparse|threading|socket|io|os|random)\..*"),
    ("py:class", r"(Path|Enum|IntEnum|IntFlag|Message|BusABC|Callable|Iterable|Iterator)"),
    # internal types that public signatures name; they are not part of the API reference
    ("py:class", r"canergy\.core\.table\.RuleTable|Cell|S|Variant|SupervisorCore"),
    ("py:class", r"canergy\.core\.supervisor\.SupervisorCore"),
    ("py:class", r"Clock|HostBeat|GuardedDevices|GuardedDevice|Intrusions|Refusals"),
    ("py:class", r"canergy\.live\.supervisor\.intrusions\.(Intrusions|Refusals)"),
    ("py:class", r"(canergy\.auth\.frames\.)?(Verdict|FrameAuth)"),
    ("py:class", r"(canergy\.live\.supervisor\.control\.)?ControlServer"),
    ("py:class", r"(canergy\.inspect\.candump\.)?FrameLog"),
    ("py:obj", r"canergy\.bridge\.schedule\.T"),  # Held's TypeVar
    ("py:class", r"'dict\[str"),  # a quoted annotation Sphinx splits at its comma
]

linkcheck_ignore = [r"https?://.*"]
"""scripts/docs checks internal links only (no network)."""
