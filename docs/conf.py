"""Sphinx configuration of emccdcal's site: ``make docs`` builds it into docs/_build/html.

The pages are the Markdown files beside this one (MyST); the API reference comes from
the docstrings (autodoc, autosummary, napoleon for the NumPy style), the command
reference from the argument parsers (sphinx-argparse), the gallery from the scripts in
``examples/``, executed at build time on small simulated data (sphinx-gallery). Nothing
is fetched from the network: no intersphinx inventory, no remote image or font.
"""

from __future__ import annotations

import os
from pathlib import Path

import emccdcal

ROOT = Path(__file__).resolve().parents[1]

project = "emccdcal"
author = "emccdcal developers"
copyright = "2026, emccdcal developers"
release = emccdcal.__version__
version = release

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
    "sphinxarg.ext",
    "sphinx_gallery.gen_gallery",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = [
    "_build",
    "auto_examples/*.ipynb",
    "auto_examples/*.py",
    "auto_examples/*.zip",
    "auto_examples/*.json",
    "auto_examples/*.md5",
    "auto_examples/*.codeobj.json",
    "sg_execution_times.rst",
]

# MyST: the pages link to one another as files (``[x](results.md)``); headings get anchors.
myst_enable_extensions = ["colon_fence"]
myst_heading_anchors = 3

# autodoc: signatures as written, the docstrings in the NumPy style.
autosummary_generate = True
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_typehints = "none"  # the docstrings state types and units
autodoc_member_order = "bysource"
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_rtype = False
napoleon_preprocess_types = False
# "ndarray, shape (R, C)" in a docstring's types is words, not a reference to one of the
# classes' ``shape`` attributes: an ambiguous reference is left as text, unwarned.
suppress_warnings = ["ref.python"]

html_theme = "pydata_sphinx_theme"
html_title = f"emccdcal {release}"
html_static_path = []
html_theme_options = {
    "navigation_with_keys": False,
    "header_links_before_dropdown": 5,  # the five sections, none behind "More"
    "show_toc_level": 2,
    "footer_start": ["copyright"],
    "footer_end": ["sphinx-version"],
}
html_show_sourcelink = False
html_sidebars = {"index": []}  # the landing page: its sections are the top bar

# The gallery: every examples/plot_*.py runs at build time, its figures kept.
sphinx_gallery_conf = {
    "examples_dirs": str(ROOT / "examples"),
    "gallery_dirs": "auto_examples",
    "filename_pattern": r"/plot_",
    "download_all_examples": False,
    "remove_config_comments": True,
    "show_memory": False,
    "plot_gallery": "True",
    "within_subsection_order": "FileNameSortKey",
    "matplotlib_animations": False,
    "reset_modules": ("matplotlib",),
    "abort_on_example_error": True,
}

# Matplotlib draws without a display.
os.environ.setdefault("MPLBACKEND", "Agg")


# --------------------------------------------------------------------------------------
# Paths of pages as links. The docstrings and the command line's help name pages as
# "docs/results.md", which a reader of the source or of ``--help`` can open; on the site
# each becomes a link to that page, titled with the page's title.
# --------------------------------------------------------------------------------------
import re  # noqa: E402

from docutils import nodes  # noqa: E402

_PAGE = re.compile(r"docs/([a-z0-9-]+)\.(?:md|rst)(#[a-z0-9-]+)?")


def _page_link(app, docname, match):
    stem, anchor = match.group(1), match.group(2) or ""
    if stem not in app.env.all_docs:
        return None
    title = app.env.titles[stem].astext()
    uri = app.builder.get_relative_uri(docname, stem) + anchor
    return nodes.reference("", title, refuri=uri, internal=True)


def _link_page_paths(app, doctree, docname):
    for text in list(doctree.findall(nodes.Text)):
        parent = text.parent
        if isinstance(parent, (nodes.FixedTextElement, nodes.reference)):
            continue  # a code block shows what a program prints, as it prints it
        value = str(text)
        if "docs/" not in value:
            continue
        whole = _PAGE.fullmatch(value.strip("`"))
        if isinstance(parent, nodes.literal) and whole:  # ``docs/x.md``: the link alone
            link = _page_link(app, docname, whole)
            if link is not None:
                parent.parent.replace(parent, link)
            continue
        pieces, last = [], 0
        for match in _PAGE.finditer(value):
            link = _page_link(app, docname, match)
            if link is None:
                continue
            pieces += [nodes.Text(value[last : match.start()]), link]
            last = match.end()
        if pieces:
            parent.replace(text, [*pieces, nodes.Text(value[last:])])


def _public_names() -> dict:
    """Where each public object is defined -> its public name: a docstring may name
    ``emccdcal.result.load_calibration``, whose page is ``emccdcal.load_calibration``."""
    return {
        f"{module}.{attribute}": f"emccdcal.{name}"
        for name, (module, attribute) in emccdcal._API.items()
        if attribute is not None
    }


_PUBLIC = _public_names()


def _link_public_names(app, env, node, contnode):
    """A reference to a public object by the module that defines it goes to its page."""
    public = _PUBLIC.get(node.get("reftarget", ""))
    if node.get("refdomain") != "py" or public is None:
        return None
    domain = env.get_domain("py")
    return domain.resolve_xref(
        env, node["refdoc"], app.builder, node["reftype"], public, node, contnode
    )


def setup(app):
    app.connect("doctree-resolved", _link_page_paths)
    app.connect("missing-reference", _link_public_names)
