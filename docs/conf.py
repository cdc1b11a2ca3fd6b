"""Sphinx configuration of the rollingstar documentation site (``make docs``).

The pages are the Markdown files of this folder (MyST); the plugin and config references are
generated at build time from the plugins' ``Params`` models and the shipped configs
(:mod:`rollingstar.pipelines.plugin_docs`), and the API reference from the docstrings (autodoc).
Warnings are errors (``make docs`` passes ``-W``).
"""
from __future__ import annotations

from pathlib import Path

from rollingstar import __version__

HERE = Path(__file__).resolve().parent

project = "rollingstar"
release = version = __version__
extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.autosummary", "sphinx.ext.mathjax"]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
exclude_patterns = ["_build", "comparison/*/report.html", "**/.ipynb_checkpoints"]
myst_enable_extensions = ["colon_fence", "dollarmath"]
myst_heading_anchors = 3
html_theme = "furo"
html_title = f"rollingstar {version}"
autosummary_generate = True
autodoc_default_options = {"members": True, "undoc-members": False, "show-inheritance": True}
autodoc_typehints = "description"
autodoc_member_order = "bysource"
# re-exported names (rollingstar.logs.LogWriter and rollingstar.logs.writer.LogWriter) make short
# cross-references ambiguous; both targets are the same object
suppress_warnings = ["ref.python"]


def _generate(app) -> None:
    """Write the generated reference pages (plugins, configs) into ``_generated/`` before reading."""
    from rollingstar.pipelines.reference_pages import write_reference_pages

    write_reference_pages(HERE / "_generated")


def setup(app):
    from pygments.lexers.special import TextLexer

    app.add_lexer("csv", TextLexer)  # the log format's CSV examples, shown as they are
    app.connect("builder-inited", _generate)
