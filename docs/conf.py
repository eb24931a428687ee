"""Sphinx configuration of the sb3-detc documentation: ``make docs`` builds it into ``docs/_build/html``."""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # autodoc imports the package of this checkout

import sb3_detc  # noqa: E402  (after the path is set)

project = "sb3-detc"
author = "sb3-detc contributors"
copyright = "2026, sb3-detc contributors"  # noqa: A001  (Sphinx's name)
release = sb3_detc.__version__
version = release

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
]
source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build"]

# MyST: ::: fenced notes, anchors for headings down to level 3 (links like page.md#heading).
myst_enable_extensions = ["colon_fence"]
myst_heading_anchors = 3

# Autodoc: members in the order of the source, signatures without the types (they are in the
# parameter lists), the constructor's parameters under the class.
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_typehints_description_target = "documented"
autoclass_content = "class"
autodoc_default_options = {"members": True, "show-inheritance": True}

html_theme = "sphinx_rtd_theme"
html_title = f"sb3-detc {release}"
html_static_path = []
