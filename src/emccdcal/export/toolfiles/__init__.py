"""emccdcal's own localization tools and formats, one module per tool: its writer (what
``export --to`` writes), its reader and the recogniser of its files (what ``audit``
reads), and the :class:`emccdcal.plugins.Tool` that pairs them, registered in
``pyproject.toml`` under ``emccdcal.tools`` as another package's would be.

Each recognises its own files only (by a suffix, or by keys no other tool's file has),
so the order in which an audit asks does not matter.
"""

from ..._lazy import submodules as _submodules

# its modules as attributes, imported on first use (as after `import emccdcal`)
__getattr__, __dir__ = _submodules(__name__, __path__)
