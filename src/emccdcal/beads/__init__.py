"""Beads: :mod:`~emccdcal.beads.fit` (exact-noise spot fits),
:mod:`~emccdcal.beads.validation` (the bead consistency test of a calibration) and
:mod:`~emccdcal.beads.cots` (calibration-on-the-spot). Never imports the report."""

from .._lazy import submodules as _submodules

# its modules as attributes, imported on first use (as after `import emccdcal`)
__getattr__, __dir__ = _submodules(__name__, __path__)
