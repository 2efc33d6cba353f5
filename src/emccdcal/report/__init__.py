"""What people look at: :mod:`~emccdcal.report.figures` (the paper's figures),
:mod:`~emccdcal.report.html` (the self-contained HTML report) and
:mod:`~emccdcal.report.corner` (corner plots of posterior samples)."""

from .._lazy import submodules as _submodules

# its modules as attributes, imported on first use (as after `import emccdcal`)
__getattr__, __dir__ = _submodules(__name__, __path__)
