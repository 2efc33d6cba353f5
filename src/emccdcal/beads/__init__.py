"""Beads: :mod:`~emccdcal.beads.fit` (exact-noise spot fits),
:mod:`~emccdcal.beads.validation` (the bead consistency test of a calibration) and
:mod:`~emccdcal.beads.cots` (calibration-on-the-spot). Never imports the report."""
