"""Stationarity of a series: the drift of its per-frame means (:func:`drift_test`, :func:`linear_drift`) and the ADF and KPSS tests (:func:`stationarity`); the thresholds every check of the package uses."""

from __future__ import annotations

import math
import warnings

import numpy as np

from ... import defaults
from ...errors import (
    InputError,
)


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


# --------------------------------------------------------------------------------------
# Small helpers
# --------------------------------------------------------------------------------------
def _pixels(mask: np.ndarray) -> list[list[int]]:
    """Coordinates [row, col] of the True pixels, at most :data:`MAX_LISTED`."""
    rc = np.argwhere(mask)[:MAX_LISTED]
    return [[int(r), int(c)] for r, c in rc]


def robust_spread(values, floor: float = 0.0) -> tuple[float, float]:
    """The median of ``values`` and their robust SD (1.4826 × the median absolute
    deviation), at least ``floor``: the yardstick hot and dead pixels are measured by
    (a population of near-equal pixels is not all outliers by its noise)."""
    median = float(np.median(values))
    return median, max(_MAD_TO_SD * float(np.median(np.abs(values - median))), floor)


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
