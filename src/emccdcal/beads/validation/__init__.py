"""Bead validation: does a calibration give every bead the same intensity at every set-point?

The paper's independent test of a calibration (Ryan et al. 2021, Figs. 4–5;
docs/beads.md). Beads are imaged at every gain set-point; their photoelectron count per frame does
not depend on the camera's gain, so under a correct calibration (φ and the gain at every
set-point) the fitted intensities agree across set-points. Under a wrong gain g' at a
set-point the intensities there are scaled by about g/g'.

For bead b, set-point k and frame f, let N_bkf be the fitted intensity (e⁻,
:func:`emccdcal.beads.fit.fit_beads`) and m_bk its mean over the converged frames. The metric
is the spread of a bead's per-set-point means, scaled to its 1× mean:

    σ_means,incl(b) = std_k { m_bk / m_b1 : all set-points }
    σ_means,excl(b) = std_k { m_bk / m_b1 : set-points other than 1× }

(dimensionless; lower is better). The headline uses **ddof = 0** (the population SD of
the set-points' means; the paper does not say which it used) and ``validation.json``
reports ddof = 1 beside it. A calibration's value is the mean over its beads. Because the
1× intensities depend only on φ, the metric tests each gain against the 1× anchor.

Each calibration's beads are fitted twice: at every set-point with each bead's shape and
background shared by its frames, then again with each bead's width pooled over the
set-points (:func:`emccdcal.beads.psf_check.shared_widths`), so that a width error cannot
differ between set-points; the second pass gives the intensities (or, with ``psf=
"residual"``, a third pass with each bead's oversampled residual image added to the
spot: the paper's second pass, the image built on one half of the frames and its fit
scored on the other). ``converged_fraction`` says per set-point how many frames
converged, and below 99 % a warning says so.

What real beads do besides is measured, reported and, by default, undone before the
set-points are compared: bleaching (:func:`intensity_trend`, from the frames' own time
course and from a set-point recorded more than once), blinking (:func:`blinking_level`:
the "on" level of a two-level mixture), and a PSF that the Gaussian does not describe
(``psf_mismatch``, with a warning).

``emccdcal validate BEAD_MANIFEST --calibration A.nc [--calibration B.nc ...] -o OUT``
fits the beads under every calibration and writes ``OUT/validation.json``,
``OUT/intensities.nc`` and the figures; ``docs/beads.md`` describes them.

Calibrations
------------
A ``--calibration`` is a calibration result (``calibration.nc`` or its directory) or a
comma-joined group of them whose set-points are merged into one calibration: φ from the
member that measured it (``is-adu`` or ``mv-adu``; else from the first member) and the
gain at each set-point from the member that has it (``is-gain`` results hold one
set-point each). The gain at 1× is 1 by definition, so a calibration needs a gain for
every other set-point of the bead manifest. Pixels that did not converge count as
missing; a bead whose box has a missing value is left out for that calibration.
"""

from .document import data_checks, format_table, read_validation
from .metric import (
    DDOF,
    INTENSITIES_FILE,
    VALIDATION_FILE,
    blinking_level,
    consistency,
    intensity_trend,
)
from .run import BeadFits, fit_validation, validate, validation_document

__all__ = [
    "VALIDATION_FILE",
    "INTENSITIES_FILE",
    "DDOF",
    "consistency",
    "intensity_trend",
    "blinking_level",
    "validate",
    "fit_validation",
    "validation_document",
    "BeadFits",
    "read_validation",
    "format_table",
    "data_checks",
]
