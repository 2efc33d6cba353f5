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

from __future__ import annotations

import math
import warnings

import numpy as np

from .. import defaults
from ..errors import (
    DataQualityWarning,
    DriftWarning,
    Finding,
    InputError,
    ReadNoiseGrowthWarning,
    SaturationWarning,
)
from .dark import as_stack, check_read_noise_growth, maps_from_dark

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

#: Fewest values (frames) the drift and stationarity tests accept: a trend's
#: autocorrelation-robust error, ADF and KPSS need a few dozen points to mean anything.
MIN_FRAMES = 50
#: Significance level of the ADF and KPSS tests (per acquisition).
DEFAULT_ALPHA = 0.05
#: Family-wise significance level of the drift test over the acquisitions of a manifest.
DRIFT_ALPHA = defaults.DRIFT_ALPHA
#: Smallest |drift| over an acquisition, in % of the mean level, that is a finding. A
#: tenth of a percent is below the statistical error of a pixel's E at the paper's
#: scale (≈ 0.2 % for 100 e⁻ in 5000 frames) and changes the EM gain by ~E·10⁻⁷
#: (docs/quality.md): a smaller drift, however significant, changes no estimate.
DEFAULT_DRIFT_THRESHOLD = defaults.DEFAULT_DRIFT_THRESHOLD
#: Robust standard deviations from the median pixel mean that make a pixel hot or dead.
DEFAULT_K = defaults.DEFAULT_K
#: Most pixel coordinates listed per category in a report (counts are always complete).
MAX_LISTED = 100
#: Fewest pixels for the hot/dead test (a robust spread needs a few pixels).
_MIN_PIXELS_DEFECTS = 5
#: MAD → standard deviation for normal data.
_MAD_TO_SD = 1.482602218505602
#: Elements (frames × pixels) converted to float64 at a time when streaming a stack.
_CHUNK_ELEMENTS = 2**23


# --------------------------------------------------------------------------------------
# Small helpers
# --------------------------------------------------------------------------------------
def _pixels(mask: np.ndarray) -> list[list[int]]:
    """Coordinates [row, col] of the True pixels, at most :data:`MAX_LISTED`."""
    rc = np.argwhere(mask)[:MAX_LISTED]
    return [[int(r), int(c)] for r, c in rc]


def _has_result_object(func) -> bool:
    """Whether a statsmodels test takes ``result_object`` (0.15 warns when it is not given)."""
    import inspect

    try:
        return "result_object" in inspect.signature(func).parameters
    except (TypeError, ValueError):  # pragma: no cover - uninspectable
        return False


# --------------------------------------------------------------------------------------
# Stationarity of a series
# --------------------------------------------------------------------------------------
def linear_drift(series, *, offset: float | None = None) -> dict:
    """Linear drift of a series over its length, and whether it is significant.

    Fits ``x_t = a + b·t`` (t = 0 … n−1, frames) by ordinary least squares. The drift is
    the fitted change from the first to the last frame, ``b·(n−1)``, relative to the mean
    level ``mean(x) − offset``.

    Parameters
    ----------
    series : array_like, shape (n,)
        The series (e.g. frame means, ADU), n ≥ 3, finite.
    offset : float, optional
        Subtracted from the mean before taking the ratio (ADU); default 0.

    Returns
    -------
    dict
        ``level`` (mean − offset, ADU), ``slope`` (ADU per frame), ``slope_se`` (ADU per
        frame), ``pvalue`` (two-sided t-test of slope = 0, n − 2 degrees of freedom),
        ``drift_pct`` and ``drift_pct_se`` (% of ``level`` over the series; None when the
        level is not positive, e.g. a dark).

    Notes
    -----
    The standard error and the test are the textbook OLS ones, whose null hypothesis is
    exactly a steady acquisition: independent frames of constant mean. A slow wander
    without a net trend also rejects it, rightly (it is not steady either), and then
    the drift's SE is too small for the size of the trend itself.

    Examples
    --------
    >>> d = linear_drift(100 + np.linspace(0, 1, 11))
    >>> round(d["drift_pct"], 6), round(d["drift_pct_se"], 6)
    (0.995025, 0.0)
    """
    from scipy.special import stdtr  # Student's t CDF (scipy.stats takes ~1 s to import)

    x = np.asarray(series, dtype=np.float64).ravel()
    n = x.size
    if n < 3:
        raise InputError(f"a drift needs at least 3 values, got {n}")
    if not np.all(np.isfinite(x)):
        raise InputError("series contains NaN or infinite values")
    tc = np.arange(n, dtype=np.float64) - 0.5 * (n - 1)
    sxx = float(tc @ tc)
    mean = float(x.mean())
    slope = float(tc @ (x - mean)) / sxx
    resid = x - mean - slope * tc
    slope_se = math.sqrt(float(resid @ resid) / (n - 2) / sxx)
    if slope_se > 0:
        pvalue = float(2.0 * stdtr(n - 2, -abs(slope) / slope_se))
    else:  # an exact line (or a constant)
        pvalue = 1.0 if slope == 0 else 0.0
    level = mean - (0.0 if offset is None else float(offset))
    drift_pct: float | None = None
    drift_pct_se: float | None = None
    if level > 0:
        drift_pct = 100.0 * slope * (n - 1) / level
        drift_pct_se = 100.0 * slope_se * (n - 1) / level
    return {
        "level": level,
        "slope": slope,
        "slope_se": slope_se,
        "pvalue": pvalue,
        "drift_pct": drift_pct,
        "drift_pct_se": drift_pct_se,
    }


def drift_test(
    series,
    *,
    offset: float | None = None,
    alpha: float = DRIFT_ALPHA,
    threshold: float = DEFAULT_DRIFT_THRESHOLD,
) -> dict:
    """Whether a series (the frame means of an acquisition) drifts enough to report.

    Parameters
    ----------
    series : array_like, shape (n,)
        E.g. the per-frame mean of the offset-subtracted counts (ADU); n ≥
        :data:`MIN_FRAMES`, finite.
    offset : float, optional
        Subtracted from the mean level for the drift in % (ADU); default 0.
    alpha : float, optional
        Significance level of this one test (:func:`check_manifest` divides its
        family-wise level by the number of acquisitions); default :data:`DRIFT_ALPHA`.
    threshold : float, optional
        Smallest |drift| reported, % of the level over the series (default
        :data:`DEFAULT_DRIFT_THRESHOLD`).

    Returns
    -------
    dict
        :func:`linear_drift`'s keys, ``n``, ``alpha``, ``threshold_pct`` and ``drifts``:
        the drift is significant (``pvalue < alpha``) and at least ``threshold`` in size
        (False when the drift in % is undefined, e.g. for a dark).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> steady = 100 + rng.normal(0, 1, 5000)
    >>> drift_test(steady)["drifts"], drift_test(steady * np.linspace(1, 1.005, 5000))["drifts"]
    (False, True)
    """
    if not (0 < alpha < 1):
        raise InputError(f"alpha must be between 0 and 1, got {alpha!r}")
    if not (math.isfinite(threshold) and threshold >= 0):
        raise InputError(f"the drift threshold must be a number ≥ 0 (%), got {threshold!r}")
    x = np.asarray(series, dtype=np.float64).ravel()
    if x.size < MIN_FRAMES:
        raise InputError(f"too few frames for the drift test: {x.size}, need at least {MIN_FRAMES}")
    d = linear_drift(x, offset=offset)
    drifts = d["drift_pct"] is not None and d["pvalue"] < alpha and abs(d["drift_pct"]) >= threshold
    return {
        "n": int(x.size),
        **d,
        "alpha": float(alpha),
        "threshold_pct": float(threshold),
        "drifts": bool(drifts),
    }


def stationarity(
    series,
    *,
    regression: str = "c",
    offset: float | None = None,
    drift_threshold: float = 1.0,
    alpha: float = DEFAULT_ALPHA,
) -> dict:
    """ADF and KPSS stationarity tests and the linear drift of a series.

    Runs ``statsmodels.tsa.stattools.adfuller(x, regression=regression, autolag='AIC')``
    and ``kpss(x, regression=regression, nlags='auto')`` (docs/quality.md) and
    :func:`linear_drift`. KPSS interpolates its p-value in a table and clips it to
    [0.01, 0.1]; its warning is silenced and the clip is reported in ``kpss_p_bound``.

    Parameters
    ----------
    series : array_like, shape (n,)
        The series, e.g. the per-frame mean of the offset-subtracted counts (ADU);
        n ≥ :data:`MIN_FRAMES`, finite, not constant.
    regression : {"c", "ct"}, optional
        Deterministic terms of both tests: constant (default; KPSS then tests level
        stationarity) or constant and trend.
    offset : float, optional
        Subtracted from the mean level for the drift in % (ADU); default 0. The tests do
        not depend on it.
    drift_threshold : float, optional
        |drift| in % of the level at or above which the series is not stationary
        (default 1 %; :func:`drift_test` is the rule the checks apply).
    alpha : float, optional
        Significance level of both tests (default 0.05).

    Returns
    -------
    dict
        ``n``, ``regression``, ``alpha``, ``drift_threshold_pct``;
        ``adf_stat``, ``adf_pvalue``, ``adf_usedlag``, ``adf_rejects_unit_root``
        (p < alpha);
        ``kpss_stat``, ``kpss_pvalue``, ``kpss_lags``, ``kpss_p_bound`` (``"lower"`` when
        the true p-value is ≤ 0.01, ``"upper"`` when ≥ 0.1, else None),
        ``kpss_rejects_stationarity`` (p < alpha);
        ``level``, ``slope``, ``slope_se``, ``drift_pct``, ``drift_pct_se`` (as in
        :func:`linear_drift`), ``drift_exceeds`` (|drift| ≥ threshold; False when the
        drift is undefined);
        ``stationary``: ADF rejects and KPSS does not and the drift is below threshold.

    Raises
    ------
    ValueError
        If the series has fewer than :data:`MIN_FRAMES` values ("too few frames for the
        stationarity tests"), is not finite, is constant, or an option is invalid.

    Notes
    -----
    KPSS rejects 5 % of truly stationary series at alpha = 0.05, so across many
    acquisitions an occasional KPSS finding is expected by chance.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> r = stationarity(100 + rng.normal(0, 1, 5000))
    >>> r["stationary"], round(r["kpss_pvalue"], 3)
    (True, 0.071)
    """
    from statsmodels.tools.sm_exceptions import InterpolationWarning
    from statsmodels.tsa.stattools import adfuller, kpss

    if regression not in ("c", "ct"):
        raise InputError(f"regression must be 'c' or 'ct', got {regression!r}")
    if not (0 < alpha < 1):
        raise InputError(f"alpha must be between 0 and 1, got {alpha!r}")
    if not (math.isfinite(drift_threshold) and drift_threshold > 0):
        raise InputError(f"drift_threshold must be a positive number (%), got {drift_threshold!r}")
    x = np.asarray(series, dtype=np.float64).ravel()
    if x.size < MIN_FRAMES:
        raise InputError(
            f"too few frames for the stationarity tests: {x.size}, need at least {MIN_FRAMES}"
        )
    if not np.all(np.isfinite(x)):
        raise InputError("series contains NaN or infinite values")
    if np.ptp(x) == 0:
        raise InputError("series is constant; the stationarity tests are undefined")

    adf_kw = {"result_object": False} if _has_result_object(adfuller) else {}
    adf_stat, adf_p, adf_lag, *_ = adfuller(x, regression=regression, autolag="AIC", **adf_kw)
    kpss_kw = {"result_object": False} if _has_result_object(kpss) else {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", InterpolationWarning)
        kpss_stat, kpss_p, kpss_lags, _crit = kpss(
            x, regression=regression, nlags="auto", **kpss_kw
        )
    bound = None
    if any(issubclass(w.category, InterpolationWarning) for w in caught):
        bound = "lower" if kpss_p <= 0.01 else "upper"
    drift = linear_drift(x, offset=offset)
    adf_rejects = bool(adf_p < alpha)
    kpss_rejects = bool(kpss_p < alpha)
    exceeds = drift["drift_pct"] is not None and abs(drift["drift_pct"]) >= drift_threshold
    return {
        "n": int(x.size),
        "regression": regression,
        "alpha": float(alpha),
        "drift_threshold_pct": float(drift_threshold),
        "adf_stat": float(adf_stat),
        "adf_pvalue": float(adf_p),
        "adf_usedlag": int(adf_lag),
        "adf_rejects_unit_root": adf_rejects,
        "kpss_stat": float(kpss_stat),
        "kpss_pvalue": float(kpss_p),
        "kpss_lags": int(kpss_lags),
        "kpss_p_bound": bound,
        "kpss_rejects_stationarity": kpss_rejects,
        **drift,
        "drift_exceeds": bool(exceeds),
        "stationary": bool(adf_rejects and not kpss_rejects and not exceeds),
    }


# --------------------------------------------------------------------------------------
# Per-stack checks
# --------------------------------------------------------------------------------------
def _chunks(stack: np.ndarray):
    n_frames = stack.shape[0]
    per_frame = max(1, int(np.prod(stack.shape[1:])))
    step = max(1, _CHUNK_ELEMENTS // per_frame)
    for f0 in range(0, n_frames, step):
        yield f0, np.asarray(stack[f0 : f0 + step])


class StackSummary:
    """What the data-quality checks need of one stack, accumulated part by part.

    A calibration reads each stack once, tile by tile; it adds every tile's
    :func:`band_statistics` here (:meth:`add`), and the checks then need no second read.
    Per frame: the sum of the counts over the pixels seen and whether any was saturated;
    per pixel: the mean and SD over all frames (:func:`emccdcal.data.dark.maps_from_dark`)
    and the number of saturated frames (counts at or above ``adc_max``).

    Parameters
    ----------
    n_frames : int
        Frames of the stack.
    shape : tuple of int
        (rows, cols).
    adc_max : int or None
        ADC maximum, ADU; None: saturation is not counted.
    """

    def __init__(self, n_frames: int, shape, adc_max: int | None):
        if adc_max is not None and (
            isinstance(adc_max, bool) or int(adc_max) != adc_max or adc_max < 1
        ):
            raise InputError(f"adc_max must be a positive integer, got {adc_max!r}")
        self.adc_max = None if adc_max is None else int(adc_max)
        self.n_frames = int(n_frames)
        self.shape = tuple(int(d) for d in shape)
        n_pixels = self.shape[0] * self.shape[1]
        self.frame_sums = np.zeros(self.n_frames)
        self.frame_min = np.full(self.n_frames, np.inf)
        self.frame_max = np.full(self.n_frames, -np.inf)
        self.frame_keys = np.zeros(self.n_frames, dtype=np.uint64)
        self.frame_saturated = np.zeros(self.n_frames, dtype=bool)
        self.mean = np.full(n_pixels, np.nan)  # per pixel, C order
        self.sd = np.full(n_pixels, np.nan)
        self.n_saturated = np.zeros(n_pixels, dtype=np.int64)
        self.m3 = np.full(n_pixels, np.nan)  # third central moments, where computed
        self.seen = np.zeros(n_pixels, dtype=bool)

    @classmethod
    def of(cls, stack, adc_max: int | None, *, third: bool = False) -> StackSummary:
        """The summary of a whole stack, read in bands of rows of bounded size (``third``:
        with the pixels' third moments)."""
        stack = as_stack(stack)
        out = cls(stack.shape[0], stack.shape[1:], adc_max)
        per_row = max(1, int(stack.shape[0]) * int(stack.shape[2]))
        step = max(1, _CHUNK_ELEMENTS // per_row)
        for r0 in range(0, stack.shape[1], step):
            out.add(
                r0 * stack.shape[2],
                band_statistics(np.asarray(stack[:, r0 : r0 + step]), adc_max, third=third),
            )
        return out

    @classmethod
    def of_file(
        cls, path, skip_frames: int, adc_max: int | None, *, third: bool = False
    ) -> StackSummary:
        """The summary of a stack file from ``skip_frames`` on, read band by band of rows
        into memory (:func:`emccdcal.data.stacks.read_band`): bounded memory, and no
        mapped pages counted against the process, whatever the stack's size."""
        from .stacks import read_band, stack_header

        (n, rows, cols), _ = stack_header(path)
        out = cls(n - skip_frames, (rows, cols), adc_max)
        step = max(1, _CHUNK_ELEMENTS // max(1, (n - skip_frames) * cols))
        for r0 in range(0, rows, step):
            band = read_band(path, r0, r0 + step, skip_frames)
            out.add(r0 * cols, band_statistics(band, adc_max, third=third))
        return out

    def add(self, first: int, statistics: dict) -> None:
        """Add the :func:`band_statistics` of the pixels from ``first`` on (C order)."""
        n = statistics["mean"].size
        part = slice(first, first + n)
        if self.seen[part].any():
            raise ValueError(f"pixels {first}..{first + n - 1} were already added")
        self.frame_sums += statistics["frame_sums"]
        if "frame_min" in statistics:
            np.minimum(self.frame_min, statistics["frame_min"], out=self.frame_min)
            np.maximum(self.frame_max, statistics["frame_max"], out=self.frame_max)
            # the part's place makes a frame's key depend on where its values are
            mix = np.uint64(2 * first + 1)
            with np.errstate(over="ignore"):
                self.frame_keys += statistics["frame_keys"].astype(np.uint64) * mix
        self.frame_saturated |= statistics["frame_saturated"]
        self.mean[part] = statistics["mean"].ravel()
        self.sd[part] = statistics["sd"].ravel()
        self.n_saturated[part] = statistics["n_saturated"].ravel()
        if "m3" in statistics:
            self.m3[part] = statistics["m3"].ravel()
        self.seen[part] = True

    def _complete(self):
        if not self.seen.all():
            raise ValueError(
                f"pixels {np.flatnonzero(~self.seen)[:5].tolist()}... were never added"
            )

    def frame_means(self, offset=None) -> np.ndarray:
        """Per-frame mean of the (offset-subtracted) counts over all pixels, ADU
        (as :func:`frame_means`)."""
        self._complete()
        off = 0.0 if offset is None else float(np.mean(np.asarray(offset, dtype=np.float64)))
        return self.frame_sums / (self.shape[0] * self.shape[1]) - off

    def saturation(self) -> dict:
        """As :func:`saturation`."""
        self._complete()
        n_values = int(self.n_saturated.sum())
        return {
            "adc_max": self.adc_max,
            "n_values": n_values,
            "fraction": n_values / max(1, self.n_frames * self.n_saturated.size),
            "n_frames": int(np.count_nonzero(self.frame_saturated)),
            "n_pixels": int(np.count_nonzero(self.n_saturated)),
            "pixels": _pixels(self.n_saturated.reshape(self.shape) > 0),
        }

    def frame_defects(self) -> dict:
        """Frames a camera or its software got wrong: ``constant`` (every pixel the same
        value, e.g. all zero: a dropped frame) and ``repeated`` (a frame identical to an
        earlier one: a frame written twice), each with their indices (first 10) and count."""
        self._complete()
        constant = np.flatnonzero(self.frame_min == self.frame_max)
        _, first = np.unique(self.frame_keys, return_index=True)
        repeated = np.setdiff1d(np.arange(self.n_frames), first)
        repeated = repeated[~np.isin(repeated, constant)]  # said once, as constant
        return {
            "n_constant": int(constant.size),
            "constant": constant[:10].tolist(),
            "n_repeated": int(repeated.size),
            "repeated": repeated[:10].tolist(),
        }

    def offset_position(self, offset) -> dict:
        """Where the offset map lies against the pixels' mean counts: ``n_pixels``,
        ``n_below_offset`` (pixels whose mean count is below their offset) and
        ``above_data`` (more than half of them: the offset cannot be this data's)."""
        self._complete()
        below = self.mean < np.broadcast_to(np.asarray(offset, float), self.shape).ravel()
        return {
            "n_pixels": int(below.size),
            "n_below_offset": int(below.sum()),
            "above_data": bool(2 * below.sum() > below.size),
        }

    def multiplication_ratio(self, offset, read_noise) -> dict | None:
        """Whether counts taken as 1× look EM-multiplied, from their first three cumulants.

        With κ₁ = mean − offset, κ₂ = variance − σ² and κ₃ the third central moment
        (Gaussian read noise adds nothing to it), R = κ₃κ₁/κ₂² is 1 for Poisson
        photoelectrons times any φ, and 1.5 once an EM register multiplies them
        (gamma model: κ₃ = 6Eg³, κ₂ = 2Eg², κ₁ = Eg, in electrons), whatever E, g and φ.
        Returns ``R`` (mean over pixels), ``R_se``, ``n_pixels`` and ``multiplied``
        (R closer to 1.5 than to 1 and above 1 by more than four standard errors), or
        None when the third moments were not gathered or fewer than 3 pixels qualify.
        """
        self._complete()
        k1 = self.mean - np.broadcast_to(np.asarray(offset, float), self.shape).ravel()
        k2 = self.sd**2 - np.broadcast_to(np.asarray(read_noise, float), self.shape).ravel() ** 2
        good = np.isfinite(self.m3) & (k1 > 0) & (k2 > 0)
        if good.sum() < 3:
            return None
        ratio = self.m3[good] * k1[good] / k2[good] ** 2
        r, se = float(ratio.mean()), float(ratio.std(ddof=1) / math.sqrt(ratio.size))
        return {
            "R": r,
            "R_se": se,
            "n_pixels": int(ratio.size),
            "multiplied": bool(r > 1.25 and r - 1 > 4 * se),
        }

    def defects(self, offset=None, *, k: float = DEFAULT_K) -> dict:
        """As :func:`pixel_defects`."""
        self._complete()
        return _defects(
            self.mean.reshape(self.shape), self.sd.reshape(self.shape), self.n_frames, offset, k
        )


def _frame_keys(flat: np.ndarray) -> np.ndarray:
    """A 64-bit fingerprint of each frame's part (frames, pixels): equal frames give
    equal keys, different ones almost surely not. A stack's key per frame is the sum of
    its parts' keys (:meth:`StackSummary.add`), whatever the order they come in."""
    import zlib

    rows = np.ascontiguousarray(flat)
    crc = [
        zlib.crc32(rows[i].tobytes()) ^ (zlib.adler32(rows[i].tobytes()) << 32)
        for i in range(rows.shape[0])
    ]
    return np.array(crc, dtype=np.uint64)


def band_statistics(band: np.ndarray, adc_max: int | None, *, third: bool = False) -> dict:
    """What a :class:`StackSummary` needs of a band of rows held in memory.

    Parameters
    ----------
    band : ndarray, shape (frames, h, cols)
        Raw counts, ADU.
    adc_max : int or None
        ADC maximum, ADU.

    third : bool, optional
        Also ``m3`` (h, cols), the third central moment of each pixel's counts (ADU³),
        for :meth:`StackSummary.multiplication_ratio`.

    Returns
    -------
    dict of ndarray
        ``frame_sums`` (frames,), ``frame_saturated`` (frames,), ``mean``, ``sd`` and
        ``n_saturated`` (h, cols): small enough to keep for every band of a full sensor.
    """
    n = band.shape[0]
    mean, sd = maps_from_dark(band) if n >= 2 else (band[0].astype(float), np.zeros(band.shape[1:]))
    if adc_max is None:
        sat_frames: np.ndarray = np.zeros(n, dtype=bool)
        sat_pixels = np.zeros(band.shape[1:], dtype=np.int64)
    else:
        sat = band >= adc_max
        sat_frames = np.asarray(sat.reshape(n, -1).any(axis=1))
        sat_pixels = sat.sum(axis=0, dtype=np.int64)
    flat = band.reshape(n, -1)
    out = {
        "frame_sums": flat.sum(axis=1, dtype=np.float64),
        "frame_min": flat.min(axis=1).astype(np.float64),
        "frame_max": flat.max(axis=1).astype(np.float64),
        "frame_keys": _frame_keys(flat),
        "frame_saturated": sat_frames,
        "mean": mean,
        "sd": sd,
        "n_saturated": sat_pixels,
    }
    if third:  # of 1× data, for multiplication_ratio
        m3 = np.zeros(band.shape[1:])
        step = max(1, _CHUNK_ELEMENTS // max(1, mean.size))  # frames converted at a time
        for f0 in range(0, n, step):
            dev = np.asarray(band[f0 : f0 + step], float) - mean
            m3 += np.einsum("fij,fij,fij->ij", dev, dev, dev)
        out["m3"] = m3 / n
    return out


def _defects(mean, sd, n_frames, offset, k) -> dict:
    """Hot, dead and stuck pixels from per-pixel means and SDs (:func:`pixel_defects`)."""
    if not (math.isfinite(k) and k > 0):
        raise InputError(f"k must be a positive number, got {k!r}")
    mean = np.asarray(mean, dtype=np.float64)
    sd = np.asarray(sd, dtype=np.float64)
    if offset is not None:
        mean = mean - np.asarray(offset, dtype=np.float64)
    stuck = sd == 0
    out = {
        "k": float(k),
        "tested": False,
        "median_mean": float(np.median(mean)),
        "robust_sd": None,
        "n_hot": 0,
        "hot": [],
        "n_dead": 0,
        "dead": [],
        "n_stuck": int(np.count_nonzero(stuck)),
        "stuck": _pixels(stuck),
    }
    if mean.size < _MIN_PIXELS_DEFECTS:
        return out
    med = float(np.median(mean))
    mad_sd = _MAD_TO_SD * float(np.median(np.abs(mean - med)))
    floor = float(np.median(sd)) / math.sqrt(n_frames)
    scale = max(mad_sd, floor)
    out.update(tested=True, robust_sd=scale)
    if scale > 0:
        z = (mean - med) / scale
        hot = z > k
        dead = z < -k
        out.update(
            n_hot=int(np.count_nonzero(hot)),
            hot=_pixels(hot),
            n_dead=int(np.count_nonzero(dead)),
            dead=_pixels(dead),
        )
    return out


def frame_means(stack, offset=None) -> np.ndarray:
    """Per-frame mean over all pixels of the (offset-subtracted) counts.

    Parameters
    ----------
    stack : array_like, shape (frames, rows, cols)
        Raw counts, ADU (a memory map is read in chunks).
    offset : float or array_like (rows, cols), optional
        Offset map S0 (ADU) subtracted from every frame; default 0.

    Returns
    -------
    ndarray of float64, shape (frames,)
        ADU.
    """
    stack = as_stack(stack)
    off = 0.0 if offset is None else float(np.mean(np.asarray(offset, dtype=np.float64)))
    out = np.empty(stack.shape[0])
    for f0, chunk in _chunks(stack):
        out[f0 : f0 + chunk.shape[0]] = chunk.reshape(chunk.shape[0], -1).mean(
            axis=1, dtype=np.float64
        )
    return out - off


def saturation(stack, adc_max: int) -> dict:
    """Count saturated values: counts at or above the ADC maximum.

    Parameters
    ----------
    stack : array_like, shape (frames, rows, cols)
        Raw counts, ADU.
    adc_max : int
        ADC maximum, ADU (``2**bits − 1``).

    Returns
    -------
    dict
        ``adc_max``; ``n_values`` (saturated pixel-frames), ``fraction`` (of all
        pixel-frames); ``n_frames`` (frames with at least one saturated pixel);
        ``n_pixels`` (pixels saturated in at least one frame) and ``pixels`` (their
        [row, col], at most :data:`MAX_LISTED`).

    Examples
    --------
    >>> s = saturation(np.array([[[1, 7]], [[7, 2]], [[3, 4]]]), adc_max=7)
    >>> s["n_values"], s["n_frames"], s["n_pixels"]
    (2, 2, 2)
    """
    stack = as_stack(stack)
    return StackSummary.of(stack, adc_max).saturation()


def pixel_defects(stack, offset=None, *, k: float = DEFAULT_K) -> dict:
    """Hot, dead and stuck pixels of a stack, by robust statistics of the pixel means.

    A pixel is *hot* when its mean count exceeds the median of all pixel means by more
    than ``k`` robust standard deviations, *dead* when it falls short by as much, and
    *stuck* when its counts never change (variance 0). The robust standard deviation is
    1.4826 × the median absolute deviation of the pixel means, floored at the median
    standard error of a pixel mean (so that a perfectly uniform sensor flags nothing by
    round-off).

    Parameters
    ----------
    stack : array_like, shape (frames, rows, cols)
        Raw counts, ADU (≥ 2 frames; a memory map is read in chunks).
    offset : float or array_like (rows, cols), optional
        Offset map S0 (ADU) subtracted from the pixel means, so that a fixed offset
        pattern does not count as a defect; default 0.
    k : float, optional
        Threshold in robust standard deviations (default 5).

    Returns
    -------
    dict
        ``k``; ``median_mean`` (ADU), ``robust_sd`` (ADU, None when there are too few
        pixels); ``n_hot``/``hot``, ``n_dead``/``dead``, ``n_stuck``/``stuck`` (counts and
        [row, col] lists, at most :data:`MAX_LISTED`); ``tested`` (False when fewer than 5
        pixels: only stuck pixels are then looked for).
    """
    stack = as_stack(stack)
    if int(stack.shape[0]) < 2:
        raise InputError(f"pixel_defects needs at least 2 frames, got {int(stack.shape[0])}")
    return StackSummary.of(stack, None).defects(offset, k=k)


def check_acquisition(
    acq,
    adc_max: int,
    *,
    k: float = DEFAULT_K,
    drift_threshold: float = DEFAULT_DRIFT_THRESHOLD,
    drift_alpha: float = DRIFT_ALPHA,
    unit_root_tests: bool = False,
    alpha: float = DEFAULT_ALPHA,
    regression: str = "c",
    summary: StackSummary | None = None,
) -> dict:
    """All data-quality checks of one acquisition.

    Parameters
    ----------
    acq : emccdcal.data.manifest.Acquisition
        The acquisition (its frames after ``skip_frames`` and its offset map are used).
    adc_max : int
        ADC maximum, ADU (``Manifest.adc_max``).
    k : float, optional
        As in :func:`pixel_defects`.
    drift_threshold, drift_alpha : float, optional
        ``threshold`` and ``alpha`` of :func:`drift_test` (this acquisition's own level).
    unit_root_tests : bool, optional
        Also run ADF and KPSS (:func:`stationarity`, with ``alpha`` and ``regression``);
        reported, never a finding. Default False.
    summary : StackSummary, optional
        The acquisition's statistics, accumulated while something else read the stack (a
        calibration does); default: read the stack now.

    Returns
    -------
    dict
        ``name``, ``frames`` (path), ``em_gain_setpoint``, ``level`` (label or None),
        ``n_frames``, ``shape``; ``drift`` (:func:`drift_test` of the per-frame mean of
        the offset-subtracted counts, None with fewer than :data:`MIN_FRAMES` frames);
        ``stationarity`` (:func:`stationarity`, or None); ``saturation``
        (:func:`saturation`); ``pixels`` (:func:`pixel_defects` on the
        offset-subtracted pixel means); ``offset``
        (:meth:`StackSummary.offset_position`); ``multiplication`` (at set-point 1:
        :meth:`StackSummary.multiplication_ratio`, else None).

    Raises
    ------
    InputError
        Naming the frames file, when its frame means cannot be tested (not finite).
    """
    path = acq.frames_path
    n = int(acq.n_frames)
    one_x = float(acq.em_gain_setpoint) == 1
    if summary is None:
        summary = StackSummary.of_file(acq.frames_path, acq.skip_frames, adc_max, third=one_x)
    series = summary.frame_means(acq.offset)
    drift = stat = None
    if n >= MIN_FRAMES:
        try:
            drift = drift_test(series, alpha=drift_alpha, threshold=drift_threshold)
            if unit_root_tests:
                stat = stationarity(series, regression=regression, alpha=alpha)
        except ValueError as exc:
            raise InputError(f"'{path}': frame means: {exc}") from None
    return {
        "name": acq.name,
        "frames": str(path),
        "em_gain_setpoint": float(acq.em_gain_setpoint),
        "level": acq.level,
        "skip_frames": int(acq.skip_frames),
        "n_frames": n,
        "shape": [int(d) for d in acq.shape],
        "drift": drift,
        "photoelectrons_estimate": _moment_photoelectrons(summary, acq, one_x),
        "stationarity": stat,
        "saturation": summary.saturation(),
        "frames_defective": summary.frame_defects(),
        "pixels": summary.defects(acq.offset, k=k),
        "offset": summary.offset_position(acq.offset),
        "multiplication": summary.multiplication_ratio(acq.offset, acq.read_noise)
        if one_x
        else None,
    }


# --------------------------------------------------------------------------------------
# Whole manifest
# --------------------------------------------------------------------------------------
def offset_from_transfer(acquisitions, summaries) -> dict | None:
    """Where the 1× levels' photon transfer says the offset is, against the offset maps.

    At 1× the excess variance is linear in the signal through the offset: var − σ² =
    (mean − S₀)/φ. A curve through each pixel's levels, fitted against ``mean − offset
    map``, therefore crosses zero excess variance where the map is wrong by ``shift`` ADU
    (positive: the true offset is above the map). The curve is a parabola, not a line: a
    steady lamp's small drift or an ADC's slight non-linearity bends the transfer at
    high signal, which would move a straight line's crossing by tens of ADU (93 ADU on
    the ProEM intensity series).

    Returns
    -------
    dict or None
        ``n_levels``, ``n_pixels``, ``shift`` (median over pixels, ADU), ``shift_se``
        (1.4826 MAD/√n), ``off`` (|shift| > 5 SE and > 1 ADU); None with fewer than 4
        set-point-1 acquisitions or 5 pixels.
    """
    idx = [i for i, a in enumerate(acquisitions) if float(a.em_gain_setpoint) == 1]
    if len(idx) < 4 or summaries[idx[0]].mean.size < 5:
        return None
    x = np.stack([summaries[i].mean - acquisitions[i].offset.ravel() for i in idx], axis=1)
    y = np.stack(
        [summaries[i].sd ** 2 - acquisitions[i].read_noise.ravel() ** 2 for i in idx], axis=1
    )
    scale = np.maximum(np.abs(x).max(axis=1, keepdims=True), 1.0)  # conditioning
    design = np.stack([np.ones_like(x), x / scale, (x / scale) ** 2], axis=2)  # (P, A, 3)
    try:
        coef = np.linalg.solve(
            np.einsum("pak,pal->pkl", design, design), np.einsum("pak,pa->pk", design, y)[..., None]
        )[..., 0]
    except np.linalg.LinAlgError:  # levels that do not differ
        return None
    with np.errstate(invalid="ignore", divide="ignore"):
        shift = -coef[:, 0] / coef[:, 1] * scale[:, 0]  # first order: where y reaches 0
    shift = shift[np.isfinite(shift) & (coef[:, 1] > 0)]
    if shift.size < 5:
        return None
    med = float(np.median(shift))
    se = _MAD_TO_SD * float(np.median(np.abs(shift - med))) / math.sqrt(shift.size)
    return {
        "n_levels": len(idx),
        "n_pixels": int(shift.size),
        "shift": med,
        "shift_se": se,
        "off": bool(abs(med) > 5 * se and abs(med) > 1.0),
    }


def _fmt_pixels(pixels: list, n: int) -> str:
    shown = ", ".join(f"({r},{c})" for r, c in pixels[:5])
    return shown + (f" and {n - 5} more" if n > 5 else "")


def _steady_cell(d: dict) -> str:
    """The table's verdict with its reason: the rule is p below α and the size above the
    threshold, so a large drift with a large SE is steady and a smaller precise one not."""
    if d["drifts"]:
        return "NO"
    if d["pvalue"] < d["alpha"]:
        return f"yes: < {d['threshold_pct']:g} %"
    return f"yes: p ≥ {d['alpha']:.2g}"


def _moment_photoelectrons(summary, acq, one_x: bool) -> float | None:
    """E (e⁻ per pixel per frame) from the counts' moments alone, median over pixels:
    F²·(mean − S0)²/(var − σ²), F² = 1 at 1× and 2 multiplied (no φ or g needed); for
    saying what a finding does at this acquisition's own level. None where undefined."""
    signal = summary.mean - np.ravel(acq.offset)
    excess = summary.sd**2 - np.ravel(acq.read_noise) ** 2
    ok = (signal > 0) & (excess > 0)
    if not ok.any():
        return None
    return float(np.median((1.0 if one_x else 2.0) * signal[ok] ** 2 / excess[ok]))


def _drift_bias_pct(drift_pct: float, photoelectrons: float, multiplied: bool) -> float:
    """Bias (%) of the EM gain (``multiplied``) or of φ (at 1×) from a linear drift of E.

    A linear drift d (fraction) spreads E uniformly over E(1 ± d/2): variance E²d²/12
    added to the count's own, 2E for the multiplied Poisson count (in units of g²) and
    E at 1×. A fit of the histogram's shape reads it as EM gain, g(1 + E·d²/24), or at 1×
    as a smaller φ (e⁻/ADU), φ(1 − E·d²/12), to first order.
    """
    excess = photoelectrons * (drift_pct / 100.0) ** 2 / 12.0
    return 100.0 * (excess / 2.0 if multiplied else -excess)


def _leave_out(a: dict) -> str:
    """How to leave one acquisition out of a calibration (its manifest table)."""
    which = f'level = "{a["level"]}"' if a.get("level") else f'frames = "{a["frames"]}"'
    return f"delete its [[acquisition]] table ({which}) from the manifest and calibrate again"


#: How a drift finding says that its bias exceeds the estimate's standard error: of an
#: estimate pooled over levels (a check to make), or of the acquisition's own.
_MAY_NOT_STAND = "the result may not stand"
_DOES_NOT_STAND = "the result does not stand as it is"


def _doubtful(text: str) -> Finding:
    """A finding after which the result does not stand as it is (the verdict says so)."""
    return Finding(text, DataQualityWarning, doubtful=True)


def _drift_effect(a: dict) -> str:
    """What a drift of one acquisition does to the result, whether it stands, and the fix."""
    d = a["drift"]
    multiplied = a["em_gain_setpoint"] != 1
    E = a.get("photoelectrons_estimate")
    light = (
        (
            f"this acquisition's {E:.4g} e⁻ per pixel and frame"
            + (" (as fitted)" if a.get("photoelectrons_source") == "fit" else "")
        )
        if E
        else ""
    )
    if a.get("drift_absorbed") is False:
        return (
            "This method takes the estimates here from the acquisition's mean (φ given, "
            + ("the gain at 1× is 1)" if not multiplied else "E shared with the 1× light)")
            + ", which a drift does not move: the result stands, and the drift's spread "
            "only lowers this acquisition's goodness of fit"
            + (
                ""
                if not multiplied
                else ", provided the light's average was the same at every set-point (a source "
                "that drifts over the session breaks that: 'calibrate --method "
                "gs-hierarchical' fits the light of each set-point)"
            )
        )
    what = "EM gain g" if multiplied else "φ (e⁻/ADU)"
    head = "The estimate is the acquisition's average, and the drift's spread reads as noise: "
    if not E:
        return (
            head + f"{what} is biased by an amount that grows with the illumination; "
            "where that is below the estimate's standard error (the summary's ±) the "
            "result stands"
        )
    bias = _drift_bias_pct(d["drift_pct"], E, multiplied)
    head += f"{what} is biased by about {bias:+.2g} % at {light}"
    fix = (
        "steady the source (warm it up, stabilise its power) and record again, or leave "
        "this acquisition out: " + _leave_out(a)
    )
    rse = a.get("estimate_relative_se")
    if not rse:
        return (
            head + "; where that bias is below the estimate's standard error (the "
            f"summary's ±) the result stands; where not, {fix}"
        )
    times = abs(bias) / (100 * rse)
    se = f"{times:.2g} times its standard error ({100 * rse:.2g} % per pixel)"
    if a.get("level") is not None and not multiplied:
        # φ pools every level of an intensity series: this level biases it by its share
        return (
            head
            + f"; φ pools every level, so its bias is at most that, {se}: "
            + (
                "the result stands"
                if times < 1
                else f"{_MAY_NOT_STAND}: leave this acquisition out to see how far φ "
                f"moves ({_leave_out(a)}); if it moves beyond its standard error, steady "
                "the source and record again"
            )
        )
    return (
        head
        + f"; that is {se}, so "
        + ("the result stands" if times < 1 else f"{_DOES_NOT_STAND}: {fix}")
    )


def _findings(a: dict) -> list[str]:
    """Human-readable warnings of one acquisition's checks: what was found, whether the
    result stands, and what fixes it."""
    name = f"{a['name']} (set-point {a['em_gain_setpoint']:g})"
    d = a["drift"]
    out = []
    if d is None:
        out.append(
            f"{name}: {a['n_frames']} frames are too few for the drift test "
            f"(at least {MIN_FRAMES}); the illumination's steadiness is unchecked: the "
            f"result stands if the source was steady; record {MIN_FRAMES} frames or "
            "more to check it"
        )
    elif d["drifts"]:
        effect = _drift_effect(a)
        out.append(
            Finding(
                f"{name}: the frame mean drifts by {d['drift_pct']:+.2f} ± "
                f"{d['drift_pct_se']:.2f} % over the acquisition (p = {d['pvalue']:.1g}): "
                f"the illumination or the EM gain is not steady. {effect}.",
                DriftWarning,
                doubtful=_DOES_NOT_STAND in effect,
                caution=_MAY_NOT_STAND in effect,
            )
        )
    off = a.get("offset")
    if off and off["above_data"]:
        out.append(
            _doubtful(
                f"{name}: the offset map lies above the mean count of {off['n_below_offset']} of "
                f"{off['n_pixels']} pixels: it cannot be this data's offset (other units, another "
                "camera mode or read-out speed?), and nothing fitted from it stands: record darks "
                "in the read-out mode of these frames, give them as the acquisition's dark (or "
                "'emccdcal scan' a folder holding both) and calibrate again"
            )
        )
    mult = a.get("multiplication")
    if mult and mult["multiplied"]:
        out.append(
            _doubtful(
                f"{name}: the counts look EM-multiplied: their cumulant ratio κ₃κ₁/κ₂² is "
                f"{mult['R']:.2f} ± {mult['R_se']:.2f} over {mult['n_pixels']} pixels (1 for "
                "unmultiplied photoelectrons, 1.5 for multiplied ones): was the EM gain on for "
                "data labelled 1×? If so, the result does not stand (φ and every gain scaled by "
                "it are wrong): record the 1× "
                "acquisition with the EM gain off (or give this one its real em_gain_setpoint) "
                "and calibrate again"
            )
        )
    bad = a.get("frames_defective") or {}
    for kind, what in (
        (
            "constant",
            "have every pixel at one value (e.g. all zero): "
            "frames the camera or its software dropped",
        ),
        ("repeated", "repeat an earlier frame exactly: frames written twice"),
    ):
        if bad.get(f"n_{kind}"):
            shown = ", ".join(map(str, bad[kind])) + (", ..." if bad[f"n_{kind}"] > 10 else "")
            frames = bad[kind]
            # defects only at the start are skipped by the manifest; elsewhere the file
            # must be cut (or recorded again)
            leading = (
                len(frames) == bad[f"n_{kind}"]
                and frames[0] <= 1
                and frames == list(range(frames[0], frames[0] + len(frames)))
            )
            fix = (
                f"set skip_frames = {a.get('skip_frames', 0) + frames[-1] + 1} in its "
                "[[acquisition]] table and calibrate again"
                if leading
                else "remove them from the file (or record again) and calibrate again"
            )
            out.append(
                _doubtful(
                    f"{name}: {bad[f'n_{kind}']} of {a['n_frames']} frames {what} "
                    f"(frames {shown}); they bias every estimate, so the result does not "
                    f"stand as it is: {fix}"
                )
            )
    sat = a["saturation"]
    if sat["n_values"]:
        out.append(
            Finding(
                f"{name}: {sat['n_values']} saturated pixel-frames (counts ≥ {sat['adc_max']}, "
                f"{sat['fraction']:.2%} of its pixel-frames) in {sat['n_frames']} frames, "
                f"{sat['n_pixels']} pixels: {_fmt_pixels(sat['pixels'], sat['n_pixels'])}; "
                "they are excluded from fits, which cuts the top off those pixels' counts, so "
                "their photoelectrons and gain read low, the more the more of their frames hit "
                "the ceiling. Every other pixel's result stands; for these, lower the light (or "
                "the EM gain) until no frame saturates and record again",
                SaturationWarning,
            )
        )
    px = a["pixels"]
    for kind, what in (("hot", "above"), ("dead", "below")):
        if px[f"n_{kind}"]:
            out.append(
                f"{name}: {px[f'n_{kind}']} {kind} pixel(s), mean more than {px['k']:g} "
                f"robust SDs ({px['robust_sd']:.3g} ADU) {what} the median: "
                f"{_fmt_pixels(px[kind], px[f'n_{kind}'])}; each pixel is fitted on its "
                "own, so every other pixel's result stands; these pixels' own results are "
                "doubtful: do not use them unless they converged with standard errors like "
                "their neighbours'"
            )
    if px["n_stuck"]:
        out.append(
            f"{name}: {px['n_stuck']} stuck pixel(s) whose counts never change: "
            f"{_fmt_pixels(px['stuck'], px['n_stuck'])}; they have no result (NaN, "
            "converged = False); the others' results stand"
        )
    return out


def check_manifest(
    manifest,
    *,
    k: float = DEFAULT_K,
    drift_threshold: float = DEFAULT_DRIFT_THRESHOLD,
    drift_alpha: float = DRIFT_ALPHA,
    unit_root_tests: bool = False,
    alpha: float = DEFAULT_ALPHA,
    regression: str = "c",
    read_noise_threshold: float = 0.05,
    summaries: list[StackSummary] | None = None,
    fitted=None,
) -> dict:
    """Data-quality checks of every acquisition of a manifest, and of the read noise.

    Parameters
    ----------
    manifest : str, Path or Manifest
        The manifest file, or as :func:`emccdcal.read_manifest` returns it.
    k, drift_threshold, unit_root_tests, alpha, regression
        As in :func:`check_acquisition`.
    drift_alpha : float, optional
        Family-wise level of the drift tests over the acquisitions (default
        :data:`DRIFT_ALPHA`): each is tested at ``drift_alpha`` / number of acquisitions
        (Bonferroni), so a steady manifest gets a drift finding at most that often.
    read_noise_threshold : float, optional
        Relative growth of the median read noise over the lowest set-point that is
        reported (default 0.05), :func:`emccdcal.data.dark.check_read_noise_growth`.
    summaries : list of StackSummary, optional
        One per acquisition, in order, when the stacks were already read (a calibration
        accumulates them in its one pass over the data); default: read every stack.
    fitted : list, optional
        One per acquisition, in order: None, or what a calibration fitted there, a dict
        of ``photoelectrons`` (E, e⁻ per pixel and frame), ``absorbed`` (whether a
        drift's spread biases an estimate there) and ``relative_se`` (that estimate's,
        or None), which the findings then quote instead of the moments' rough E, and
        against which they weigh a drift's bias.

    Returns
    -------
    dict
        JSON-serialisable: ``manifest`` (path), ``adc_max``, ``acquisitions`` (name →
        :func:`check_acquisition`; a repeated name gets a ``#2``, ``#3`` … suffix),
        ``read_noise_growth`` (list of messages) and ``warnings`` (every finding as one
        human-readable string, in acquisition order, read-noise growth last).

    Raises
    ------
    ValueError
        From :func:`check_acquisition` (naming the file).

    Examples
    --------
    >>> import tempfile, emccdcal
    >>> work = tempfile.mkdtemp()
    >>> sim = emccdcal.simulate_gain_series(
    ...     f"{work}/gs", rows=4, cols=4, frames=400, setpoints=(1, 10), seed=1, progress=False
    ... )
    >>> report = emccdcal.check(sim.manifest)
    >>> sorted(report["acquisitions"]), report["warnings"]
    (['10x', '1x'], [])
    """
    if not (0 < drift_alpha < 1):
        raise InputError(f"drift_alpha must be between 0 and 1, got {drift_alpha!r}")
    if not hasattr(manifest, "acquisitions"):  # its file, as every verb takes it
        from .manifest import read_manifest

        manifest = read_manifest(manifest)
    acqs: dict[str, dict] = {}
    warn: list[str] = []
    per_test = drift_alpha / max(1, len(manifest.acquisitions))
    used = []
    for i, acq in enumerate(manifest.acquisitions):
        summary = (
            StackSummary.of_file(
                acq.frames_path,
                acq.skip_frames,
                manifest.adc_max,
                third=float(acq.em_gain_setpoint) == 1,
            )
            if summaries is None
            else summaries[i]
        )
        used.append(summary)
        res = check_acquisition(
            acq,
            manifest.adc_max,
            k=k,
            drift_threshold=drift_threshold,
            drift_alpha=per_test,
            unit_root_tests=unit_root_tests,
            alpha=alpha,
            regression=regression,
            summary=summary,
        )
        if fitted is not None and fitted[i] is not None:
            # the calibration's own estimates, where they are known
            res["photoelectrons_estimate"] = float(fitted[i]["photoelectrons"])
            res["photoelectrons_source"] = "fit"
            res["drift_absorbed"] = bool(fitted[i]["absorbed"])
            res["estimate_relative_se"] = fitted[i]["relative_se"]
        key, i = acq.name, 1
        while key in acqs:
            i += 1
            key = f"{acq.name}#{i}"
        acqs[key] = res
        warn.extend(_findings(res))
    transfer = offset_from_transfer(manifest.acquisitions, used)
    if transfer is not None and transfer["off"]:
        warn.append(
            _doubtful(
                f"set-point 1: the photon transfer of its {transfer['n_levels']} levels (variance "
                f"against mean) reaches zero excess variance {transfer['shift']:+.1f} ± "
                f"{transfer['shift_se']:.1f} ADU from the offset maps: the offsets are off by "
                "about that much (another camera mode's, or none?), which biases φ and E, so the "
                "result does not stand as it is: record darks in the read-out mode of the light "
                "frames, give them as the acquisitions' dark (or 'emccdcal scan' a folder holding "
                "both) and calibrate again"
            )
        )
    growth = check_read_noise_growth(
        [a.em_gain_setpoint for a in manifest.acquisitions],
        [a.read_noise for a in manifest.acquisitions],
        threshold=read_noise_threshold,
    )
    warn.extend(Finding(g, ReadNoiseGrowthWarning) for g in growth)
    return {
        "manifest": str(manifest.path),
        "adc_max": int(manifest.adc_max),
        "drift_alpha": float(drift_alpha),
        "acquisitions": acqs,
        "offset_from_transfer": transfer,
        "read_noise_growth": list(growth),
        "warnings": warn,
    }


def _p(p: float, bound: str | None = None) -> str:
    if math.isnan(p):
        return "n/a"
    if bound == "lower":
        return "≤0.01"
    if bound == "upper":
        return "≥0.1"
    return f"{p:.2g}" if p >= 1e-4 else "<1e-4"


def _threshold(report: dict) -> str:
    for a in report["acquisitions"].values():
        if a.get("drift") is not None:
            return f"{a['drift']['threshold_pct']:g}"
    return f"{DEFAULT_DRIFT_THRESHOLD:g}"


def format_report(report: dict) -> str:
    """A check report as a human-readable table followed by its warnings.

    Parameters
    ----------
    report : dict
        From :func:`check_manifest`.

    Returns
    -------
    str
        Multi-line text (no trailing newline).
    """
    unit_root = any(a["stationarity"] for a in report["acquisitions"].values())
    header: tuple[str, ...] = (
        "acquisition",
        "set-pt",
        "frames",
        "level ADU",
        "drift % ± SE",
        "p",
        "steady",
    )
    if unit_root:
        header += ("ADF p", "KPSS p")
    header += ("sat. values/frames/px", "hot", "dead", "stuck")
    rows: list[tuple[str, ...]] = [header]
    for name, a in report["acquisitions"].items():
        d, s, sat, px = a.get("drift"), a["stationarity"], a["saturation"], a["pixels"]
        if d is None and s is not None:  # a report of an earlier version: ADF/KPSS decided
            d = {**s, "pvalue": math.nan, "drifts": not s["stationary"]}
        if d is None:
            level, drift, p, steady = "n/a", "n/a", "n/a", "?"
        else:
            level = f"{d['level']:.1f}"
            drift = (
                "n/a"
                if d["drift_pct"] is None
                else f"{d['drift_pct']:+.2f} ± {d['drift_pct_se']:.2f}"
            )
            p, steady = _p(d["pvalue"]), _steady_cell(d)
        row: tuple[str, ...] = (
            name,
            f"{a['em_gain_setpoint']:g}",
            str(a["n_frames"]),
            level,
            drift,
            p,
            steady,
        )
        if unit_root:
            row += (
                ("n/a", "n/a")
                if s is None
                else (_p(s["adf_pvalue"]), _p(s["kpss_pvalue"], s["kpss_p_bound"]))
            )
        rows.append(
            row
            + (
                f"{sat['n_values']}/{sat['n_frames']}/{sat['n_pixels']}",
                str(px["n_hot"]) if px["tested"] else "n/a",
                str(px["n_dead"]) if px["tested"] else "n/a",
                str(px["n_stuck"]),
            )
        )
    widths = [max(len(r[i]) for r in rows) for i in range(len(header))]
    lines = [f"Data-quality checks: {report['manifest']} (ADC maximum {report['adc_max']} ADU)"]
    if "drift_alpha" in report:
        each = next(
            (a["drift"]["alpha"] for a in report["acquisitions"].values() if a.get("drift")), None
        )
        lines.append(
            f"steady: no drift of at least {_threshold(report)} % significant at a "
            f"family-wise {100 * report['drift_alpha']:g} % over the acquisitions"
            + (
                ""
                if each is None
                else f" (each p must be below {each:.2g}: "
                "a large drift with a large SE can be steady, a smaller precise one "
                "not)"
            )
        )
    for j, r in enumerate(rows):
        cells = [c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths))]
        lines.append("  ".join(cells).rstrip())
        if j == 0:
            lines.append("  ".join("-" * w for w in widths))
    if report["warnings"]:
        lines.append("")
        lines.append(f"{len(report['warnings'])} finding(s):")
        lines.extend(f"- {w}" for w in report["warnings"])
    else:
        lines.append("")
        lines.append("No findings.")
    return "\n".join(lines)
