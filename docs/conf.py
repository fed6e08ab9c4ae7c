"""Sphinx configuration of wiggly's documentation (``make docs``)."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

project = "wiggly"
author = "the wiggly authors"
copyright = "2026, the wiggly authors"

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
]

source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]

myst_enable_extensions = ["dollarmath", "amsmath", "colon_fence", "deflist"]
myst_heading_anchors = 3

autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": True, "show-inheritance": False}
napoleon_numpy_docstring = True
napoleon_google_docstring = True

html_theme = "furo"
html_title = "wiggly"
html_static_path: list[str] = []



def _plain_fields(app, what, name, obj, options, lines):
    """Render docstrings written as ``name : description`` lines (no numpydoc section header)
    as a definition list, before napoleon reads them as types."""
    if what != "class" or any(line.strip().startswith("---") for line in lines):
        return
    import re

    field = re.compile(r"^(\w[\w, ]*) : (.*)$")
    out: list[str] = []
    for line in lines:
        m = field.match(line)
        out += [f"``{m.group(1)}``", "    " + m.group(2)] if m else [line]
    lines[:] = out


def setup(app):
    app.connect("autodoc-process-docstring", _plain_fields, priority=400)
