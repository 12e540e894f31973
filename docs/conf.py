"""Sphinx configuration of the sb3-sfgpi documentation (offline: no intersphinx, nothing fetched)."""

from __future__ import annotations

import os
import sys

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, ROOT)  # document this checkout's code

import sb3_sfgpi  # noqa: E402

project = "sb3-sfgpi"
author = "sb3-sfgpi developers"
copyright = "2026, sb3-sfgpi developers"
version = release = sb3_sfgpi.__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.mathjax",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]

myst_enable_extensions = ["dollarmath", "colon_fence", "deflist"]
myst_heading_anchors = 3

autodoc_default_options = {"show-inheritance": True, "member-order": "bysource"}
autodoc_typehints = "description"
autodoc_mock_imports: list[str] = []

html_theme = "alabaster"  # built into Sphinx: nothing to install, nothing fetched
html_title = f"sb3-sfgpi {release}"
html_static_path: list[str] = []


def _package_names() -> str:
    """A Markdown list of ``sb3_sfgpi.__all__`` and ``sfgpi_envs.__all__``, each linked to where it is defined."""
    import importlib

    lines = []
    for package in ("sb3_sfgpi", "sfgpi_envs"):
        module = importlib.import_module(package)
        for name in sorted(n for n in module.__all__ if not n.startswith("_")):
            obj = getattr(module, name)
            lines.append(f"- {{py:obj}}`{package}.{name} <{obj.__module__}.{obj.__qualname__}>`")
    return "\n".join(lines)


def _fill_placeholders(app, docname, source) -> None:
    if docname == "api/index":
        source[0] = source[0].replace("{{ package_names }}", _package_names())


def setup(app):
    app.connect("source-read", _fill_placeholders)
