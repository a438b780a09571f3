"""Sphinx configuration of hamid's site: the user guide and reference pages (Markdown, read by
myst-parser) and the API reference generated from the docstrings (autodoc, napoleon).

Build: `python -m sphinx -W --keep-going -b html docs OUTDIR` (tests/test_docs_site.py does,
warnings as errors).

Sphinx rather than MkDocs: it is what numpy, scipy, pandas and matplotlib use, so their
readers know it; autodoc documents the functions from their own docstrings and signatures
with no plugin beyond the standard ones, and its `-W` turns every broken cross-reference,
missing image and unreadable docstring into an error."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))   # the working tree's hamid, as the tests import it

import hamid  # noqa: E402

project = "hamid"
author = "the hamid developers"
copyright = "the hamid developers, MIT license"   # noqa: A001 (Sphinx's name)
release = version = hamid.__version__

extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.napoleon"]
source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build"]
myst_heading_anchors = 3          # links such as output.md#many-files-fit---each
myst_enable_extensions = ["colon_fence"]

autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": True}

html_theme = "alabaster"
html_title = f"hamid {release}"
html_static_path: list[str] = []
