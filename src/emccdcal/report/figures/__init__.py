"""Figures of a calibration, modelled on Ryan et al. (2021): matplotlib, object API only.

Every function takes results (xarray datasets from :func:`emccdcal.result.load` or
:func:`emccdcal.calibrate`) and returns a :class:`matplotlib.figure.Figure`; none touches
pyplot's global state, so they are safe in scripts, servers and threads. Every axis label
ends with its unit in parentheses. :func:`save_figure` writes a figure as PNG and SVG.

========================================  =============================================
function                                  shows (paper figure)
========================================  =============================================
:func:`histogram_figure`                  each acquisition's counts of one pixel with the
                                          fitted pmf (Fig. 1); re-reads the raw data
:func:`photon_transfer_figure`            variance against mean per acquisition with the
                                          mean–variance fit lines (Fig. 2a); raw data
:func:`estimates_figure`                  distributions of per-pixel φ and gains, per
                                          method and set-point (Figs. 2b, 3)
:func:`maps_figure`                       maps of φ, gains, offset, read noise,
                                          convergence and goodness of fit
:func:`gain_figure`                       measured gain against set-point, error bars
:func:`bead_intensity_figure`             bead intensities per set-point per method
                                          (Fig. 4), from a validation directory
:func:`bead_consistency_figure`           per-bead mean intensity relative to 1× and the
                                          consistency metric (Fig. 5)
========================================  =============================================

The two raw-data figures find the data through the result's ``manifest_path`` attribute;
when the manifest is gone or has changed since the calibration they raise
:class:`DataUnavailable` (a ``ValueError`` naming the file).
"""

from .beads import bead_consistency_figure, bead_intensity_figure, write_validation_figures
from .common import DataUnavailable, default_pixel, figure_png, save_figure
from .estimates import estimates_figure, maps_figure
from .gains import (
    gain_check_figure,
    gain_curve_figure,
    gain_figure,
    gain_history_figure,
    gain_points,
    results_gain_curve_figure,
)
from .pixel import histogram_figure, photon_transfer_figure

__all__ = [
    "DataUnavailable",
    "default_pixel",
    "histogram_figure",
    "photon_transfer_figure",
    "estimates_figure",
    "maps_figure",
    "gain_figure",
    "gain_points",
    "bead_intensity_figure",
    "bead_consistency_figure",
    "save_figure",
    "figure_png",
    "write_validation_figures",
    "gain_history_figure",
    "gain_check_figure",
    "gain_curve_figure",
    "results_gain_curve_figure",
]
