"""Sphinx configuration of the API reference (docs/api).

Build it from the checkout's root, with the ``docs`` extra installed::

    python -m sphinx -W --keep-going -b html docs/api build/api
"""

from __future__ import annotations

import os
import re
import sys

# the checkout's root, so the reference documents the packages of this tree even before an install
sys.path.insert(0, os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..")))
os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # the viewer's module imports pygame on use

project = "constrained-particles"
author = "constrained-particles contributors"
copyright = "constrained-particles contributors, MIT licence"  # noqa: A001 (Sphinx's name)
release = version = "0.1.0"

extensions = ["sphinx.ext.autodoc"]

# annotations are strings (``from __future__ import annotations``): show the aliases by name
# rather than numpy's expansion of ArrayLike into a page-long union
autodoc_type_aliases = {
    "ArrayLike": "numpy.typing.ArrayLike",
    "NDArray": "numpy.typing.NDArray",
}
autodoc_member_order = "bysource"
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_typehints = "signature"
autodoc_preserve_defaults = True

root_doc = "index"
exclude_patterns = ["_build"]
html_theme = "alabaster"
html_static_path: list[str] = []
html_title = "constrained-particles API reference"


# The environments' class docstrings are written in Markdown, as Gymnasium's are (``## Action
# Space``, pipe tables, fenced examples, single-backtick code): they read as the environment's
# page in ``help()`` and in an editor. For this reference they are turned into reST here.
_HEADING = re.compile(r"^#{2,3} (.+)$")
_CODE = re.compile(r"(?<![`\w])`([^`\n]+)`(?![`\w])")


def _cells(line: str) -> list[str]:
    return [_CODE.sub(r"``\1``", cell.strip()) for cell in line.strip().strip("|").split("|")]


def _markdown_to_rest(lines: list[str]) -> list[str]:
    out: list[str] = []
    i = 0
    while i < len(lines):
        line = lines[i]
        heading = _HEADING.match(line)
        if heading:
            out += [f".. rubric:: {heading.group(1)}", ""]
        elif line.startswith("```"):
            pass  # the fenced examples are doctest blocks, which reST shows as they are
        elif line.startswith("|") and i + 1 < len(lines) and set(lines[i + 1]) <= set("|-: "):
            rows = [_cells(line)]
            i += 2
            while i < len(lines) and lines[i].startswith("|"):
                rows.append(_cells(lines[i]))
                i += 1
            out += [".. list-table::", "   :header-rows: 1", ""]
            for row in rows:
                out += [f"   * - {row[0]}"] + [f"     - {cell}" for cell in row[1:]]
            out.append("")
            continue
        else:
            out.append(_CODE.sub(r"``\1``", line))
        i += 1
    return out


def _process_docstring(app, what, name, obj, options, lines: list[str]) -> None:
    if any(_HEADING.match(line) for line in lines):
        lines[:] = _markdown_to_rest(lines)


def setup(app) -> None:
    app.connect("autodoc-process-docstring", _process_docstring)
