"""Sphinx configuration of the documentation site (pages in Markdown through MyST, the API reference
from the docstrings through autodoc). Build: ``.venv/bin/sphinx-build -W -b html docs docs/_build/html``
(tests/test_docs.py builds it with warnings as errors)."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the packages, when the docs are built from a checkout without an install

project = "smart-marl"
author = "the smart-marl authors"
copyright = "the smart-marl authors"

extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.napoleon"]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
exclude_patterns = ["_build", "images"]
myst_heading_anchors = 3  # [text](page.md#a-heading) links to headings of levels 1-3
myst_enable_extensions = ["colon_fence"]

html_theme = "furo"
html_title = "smart-marl"

autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": True, "undoc-members": False, "show-inheritance": True}
# the environment and fine-tuning modules import torch, pettingzoo and torchrl: all in the docs build's
# environment (`pip install -e ".[dev]"`), nothing is mocked, so the reference shows what really imports
