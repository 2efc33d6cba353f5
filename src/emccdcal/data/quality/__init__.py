"""Data-quality checks of calibration acquisitions, without fitting.

A calibration assumes that every acquisition is a steady exposure of a well-behaved
sensor. :func:`check_manifest` tests what can be tested from the data alone
(docs/quality.md):

* **Drift of the illumination** (:func:`drift_test`): an OLS line through the per-frame
  mean of the offset-subtracted counts gives the linear drift over the acquisition in %
  of the mean level, and a t-test of it against the steady null (independent frames of
  constant mean). A drift is a finding when it is significant at a family-wise level of
  1 % over the acquisitions of the manifest (Bonferroni) *and* at least
  :data:`DEFAULT_DRIFT_THRESHOLD` % in size. The false-alarm rate and power of this rule
  were measured on simulated calibrations (docs/quality.md).
* **Unit-root tests** (:func:`stationarity`, on request): ADF (null: unit root) and KPSS
  (null: level-stationary) of the same series, as the paper's supplementary stationarity
  tests. They are reported, not turned into findings: at a 5 % level per acquisition
  KPSS alone flags one of six steady acquisitions in about a quarter of calibrations.
* **Saturation** (:func:`saturation`): pixel-frames at or above the ADC maximum.
* **Hot, dead and stuck pixels** (:func:`pixel_defects`): pixel means far from the
  median of the pixel means in robust (MAD-based) standard deviations, and pixels whose
  counts never change.
* **Read noise growing with the set-point** (clock-induced charge in the darks,
  :func:`emccdcal.data.dark.check_read_noise_growth`).

Every result is a plain dict of floats, ints, bools, strings, lists and None, ready for
:func:`json.dumps`. :func:`format_report` prints it as a table; ``emccdcal check
MANIFEST [--json]`` does both from the command line.

Units: counts, levels and offsets in ADU; drift in % of the mean offset-subtracted level
over the whole acquisition; set-points dimensionless.
"""

from .series import check_manifest, format_report, offset_from_transfer
from .stacks import (
    StackSummary,
    band_statistics,
    check_acquisition,
    frame_means,
    pixel_defects,
    saturation,
)
from .drift import (
    DEFAULT_ALPHA,
    DEFAULT_DRIFT_THRESHOLD,
    DEFAULT_K,
    DRIFT_ALPHA,
    MAX_LISTED,
    MIN_FRAMES,
    drift_test,
    linear_drift,
    stationarity,
)

__all__ = [
    "MIN_FRAMES",
    "DEFAULT_ALPHA",
    "DEFAULT_DRIFT_THRESHOLD",
    "DEFAULT_K",
    "MAX_LISTED",
    "DRIFT_ALPHA",
    "drift_test",
    "stationarity",
    "linear_drift",
    "frame_means",
    "saturation",
    "pixel_defects",
    "check_acquisition",
    "offset_from_transfer",
    "StackSummary",
    "band_statistics",
    "check_manifest",
    "format_report",
]
