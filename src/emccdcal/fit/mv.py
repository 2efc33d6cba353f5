"""Mean–variance (photon-transfer) calibration: φ at 1× and the EM gain from moments.

These are the paper's comparison methods ``mv-adu`` and ``mv-gain`` (Ryan et al. 2021,
Eq. 5–6; docs/methods.md). They need only each pixel's sample mean and sample variance per
acquisition, are closed-form, and are vectorised over pixels: every function takes arrays
shaped ``(A, *pixels)`` — ``A`` acquisitions along the first axis, any pixel shape after it
(``(P,)`` for a block of pixels, ``(rows, cols)`` for an image) — and returns per-pixel
arrays. No Python loop runs over pixels.

Model
-----
With ``x = ⟨S⟩ − S0`` the offset-subtracted mean (ADU) and ``y = Var(S) − σ²`` the
variance above read noise (ADU²), the noise model's first two moments (docs/methods.md) give
a straight line through the origin::

    1× (Poisson–normal):            y = x / φ          (slope β = 1/φ,    Eq. 5a)
    gain g (Poisson–gamma–normal):  y = (2g/φ) · x     (slope β = 2g/φ,   Eq. 5b, 6)

so ``E = x·φ`` at 1× and ``E = x·φ/g = 2x/β`` at gain (φ cancels: ``E = 2·x²/y`` for one
level is the familiar "mean²/variance" estimate with an excess-noise factor F² = 2).

Choices, and why
----------------
* **Through the origin, read noise from the dark maps.** The intercept of the photon
  transfer line is σ², which the dark maps measure far better than an extrapolation of
  the line does, so by default we subtract the dark σ² and fit the slope alone.
  ``intercept=True`` fits ``y = a + β·x`` instead (the classical photon-transfer fit; the
  dark σ² then only shifts ``a``). The default also works with one level per fit, which is
  what a gain series has at each set-point.
* **Weighted least squares with the sampling variances of the moments.** For near-Gaussian
  counts the sample variance ``s²`` (``ddof=1``) of ``n`` frames has
  ``Var(s²) ≈ 2·v²/(n−1)`` and the sample mean ``Var(x) = v/n``, with ``v`` the total
  variance. Each point's weight is the inverse of its *effective* variance
  ``Var(y) + β²·Var(x)`` (an errors-in-variables correction; the mean's share is about
  ``β·n/(2v)``-times smaller and matters only at low signal). ``v`` is taken from the
  *fitted* line (``σ² + β·x``, or ``a + σ² + β·x``), not from the sample variance itself:
  weights computed from the noisy ``s²`` would correlate with ``y`` and bias the slope low.
  The fit starts from weights with the sample variances and is re-weighted ``iterations``
  times (3 by default; it converges in one or two). ``weighted=False`` gives ordinary
  least squares (every level counts the same, so the bright, noisy levels dominate).
* **Standard errors by first-order error propagation (delta method)** through the
  closed-form estimator, with the weights held fixed, over the sampling variances above:
  ``Var(β) = Σ_j (∂β/∂x_j)²·Var(x_j) + (∂β/∂y_j)²·Var(y_j)``, and likewise for every
  ``E`` (which is correlated with φ: both are computed from the same points). These SEs are
  model-based; they hold for unweighted fits too.
* **What the SEs leave out.** The dark maps (``offset``, ``read_noise``) are treated as
  exact; the mean and the sample variance are treated as uncorrelated (exact for symmetric
  counts; their correlation is skewness/√2, about 0.08 for PGN counts at E = 370 e⁻); and
  ``Var(s²)`` omits the fourth-cumulant term ``κ4/n``, a relative ``3/E`` (PGN) or
  ``1/(2E)``-ish (PN) correction that matters only for E of a few e⁻. Departures from the
  model itself — the excess-noise factor F² < 2 at low gain (docs/simulation.md: a bias of about
  −11 % on g at 5×), ADC non-linearity, clock-induced charge in the dark σ — are biases,
  not sampling noise, and no SE covers them. Finally φ = 1/β (and E ∝ 1/β) is a
  non-linear function of the fitted slope, so it carries a second-order bias of about
  ``φ·(SE/φ)²``: negligible at the 1–2 % precision of a good series, +0.4 % at 6 %.
* **Intervals by Fieller's theorem.** φ = 1/β and every E are ratios whose denominator,
  the slope, can be poorly determined (a set-point where the signal variance is small
  against the read noise): there ``estimate ± 1.96 SE`` is far from a 95 % interval, and
  the estimate itself is undefined where the slope comes out ≤ 0. Each fit therefore also
  returns 95 % bounds (``*_lower``, ``*_upper``) by Fieller's theorem: the set of ratios R
  for which ``a − R·b`` (numerator minus R times denominator, approximately normal) is
  within ``z`` of its standard error (:func:`fieller_interval`). They are defined where
  the estimate is not, and reach to infinity where the slope is not significantly
  positive. The gains, linear in the slope, get the interval of the slope scaled.
* **Goodness of fit.** ``chi2`` (the residual sum of squares over the effective sampling
  variances, with ``dof`` degrees of freedom) tells how well a multi-level line fits; well
  above ``dof`` means the straight line or the sampling variances do not describe the
  data, and the SEs are then too small.

Inputs
------
Pass ``var`` as the **unbiased** (``ddof=1``) sample variance of the raw counts of ``n``
frames, ``mean`` as their sample mean (ADU), and the dark maps ``offset`` (S0, ADU) and
``read_noise`` (σ, ADU) per acquisition (they broadcast, so one ``(rows, cols)`` map serves
all acquisitions at one set-point).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..errors import OptionError
from ..model import adc

__all__ = [
    "MVADUFit",
    "MVGainFit",
    "MeanRatioGains",
    "fit_mv_adu",
    "fieller_interval",
    "fit_mv_gain",
    "mean_ratio_gains",
]


_Z95 = 1.959964  # two-sided 95 % normal quantile


class MVADUFit(NamedTuple):
    """Result of :func:`fit_mv_adu`; ``pixels`` is the input's pixel shape.

    Attributes
    ----------
    e_per_adu, e_per_adu_se : ndarray, shape ``pixels``
        φ and its standard error (e⁻/ADU). NaN where the fitted slope is not positive.
    photoelectrons, photoelectrons_se : ndarray, shape ``(A, *pixels)``
        E per acquisition, ``(mean − offset)·φ``, and its standard error (e⁻ per pixel per
        frame), including the uncertainty of φ and of the mean.
    e_per_adu_lower, e_per_adu_upper : ndarray, shape ``pixels``
        95 % Fieller bounds of φ (e⁻/ADU); the upper bound is ``inf`` where the slope is not
        significantly positive. Defined also where ``e_per_adu`` is NaN.
    photoelectrons_lower, photoelectrons_upper : ndarray, shape ``(A, *pixels)``
        95 % Fieller bounds of E (e⁻).
    chi2 : ndarray, shape ``pixels``
        Σ residual² / effective variance at the fitted line (dimensionless); ≈ ``dof`` when
        the straight line and the sampling variances describe the data.
    dof : int
        Degrees of freedom of ``chi2``: ``A − 1`` (``A − 2`` with an intercept).
    valid : ndarray of bool, shape ``pixels``
        Finite, positive slope and finite standard errors.
    """

    e_per_adu: np.ndarray
    e_per_adu_se: np.ndarray
    photoelectrons: np.ndarray
    photoelectrons_se: np.ndarray
    chi2: np.ndarray
    dof: int
    valid: np.ndarray
    e_per_adu_lower: np.ndarray
    e_per_adu_upper: np.ndarray
    photoelectrons_lower: np.ndarray
    photoelectrons_upper: np.ndarray


class MVGainFit(NamedTuple):
    """Result of :func:`fit_mv_gain`; ``pixels`` is the input's pixel shape.

    Attributes
    ----------
    setpoints : ndarray, shape ``(S,)``
        The distinct set-points, ascending (float, dimensionless).
    em_gain, em_gain_se : ndarray, shape ``(S, *pixels)``
        g per set-point and its standard error (dimensionless). At set-point 1 the gain is
        1 by definition (no multiplication) with standard error 0.
    photoelectrons, photoelectrons_se : ndarray, shape ``(A, *pixels)``
        E per acquisition, ``(mean − offset)·φ/g``, and its standard error (e⁻ per pixel
        per frame). At gain this does not depend on φ (it is ``2·x/β``); at 1× it is
        ``x·φ`` and its SE includes ``e_per_adu_se``.
    em_gain_lower, em_gain_upper : ndarray, shape ``(S, *pixels)``
        95 % bounds of g: the slope's interval times φ/2 (Fieller over φ's error when
        ``e_per_adu_se`` is given), at least 0; NaN at set-point 1. Defined also where
        ``em_gain`` is NaN (a slope ≤ 0): then the upper bound says how small g must be.
    photoelectrons_lower, photoelectrons_upper : ndarray, shape ``(A, *pixels)``
        95 % Fieller bounds of E (e⁻); the upper bound is ``inf`` where the set-point's slope
        is not significantly positive (the data cannot tell E from infinity).
    chi2 : ndarray, shape ``(S, *pixels)``
        Weighted residual sum of squares of each set-point's line (0 for one level, and
        at set-point 1, which is not fitted).
    dof : ndarray of int, shape ``(S,)``
        Degrees of freedom of ``chi2`` per set-point.
    valid : ndarray of bool, shape ``pixels``
        Every set-point's slope positive and every estimate and SE finite.
    """

    setpoints: np.ndarray
    em_gain: np.ndarray
    em_gain_se: np.ndarray
    photoelectrons: np.ndarray
    photoelectrons_se: np.ndarray
    chi2: np.ndarray
    dof: np.ndarray
    valid: np.ndarray
    em_gain_lower: np.ndarray
    em_gain_upper: np.ndarray
    photoelectrons_lower: np.ndarray
    photoelectrons_upper: np.ndarray


class MeanRatioGains(NamedTuple):
    """Result of :func:`mean_ratio_gains`.

    Attributes
    ----------
    em_gain, em_gain_se : ndarray, shape ``(A, *pixels)``
        Gain of each acquisition relative to the 1× acquisition, and its standard error
        (dimensionless). The 1× row is exactly 1 with SE 0.
    """

    em_gain: np.ndarray
    em_gain_se: np.ndarray


# --------------------------------------------------------------------------------------
# Input checking
# --------------------------------------------------------------------------------------
def _moments(mean, var, offset, read_noise, n, poisson_normal=True):
    """Check and broadcast the per-acquisition moments; return x, y, the read-out's
    variance and n (all (A, ...)). The read-out's variance is σ², and the ADC's 1/12
    where ``poisson_normal`` acquisitions' σ is the analog read noise
    (:func:`emccdcal.model.adc.count_variance`)."""
    mean = np.asarray(mean, dtype=float)
    var = np.asarray(var, dtype=float)
    if mean.ndim < 1:
        raise OptionError("mean must have shape (A, *pixels): one row per acquisition")
    if mean.shape[0] < 1:
        raise OptionError("need at least 1 level (acquisition); got 0")
    if var.shape != mean.shape:
        raise OptionError(f"var has shape {var.shape} but mean has shape {mean.shape}")
    shape = mean.shape
    out = {}
    for name, value in (("offset", offset), ("read_noise", read_noise)):
        arr = np.asarray(value, dtype=float)
        try:
            out[name] = np.broadcast_to(arr, shape)
        except ValueError:
            raise OptionError(
                f"{name} has shape {arr.shape}, which does not broadcast to the shape of "
                f"mean {shape}"
            ) from None
    n_arr = np.asarray(n, dtype=float)
    if n_arr.ndim == 1 and len(shape) > 1:
        if n_arr.shape[0] != shape[0]:
            raise OptionError(
                f"n has {n_arr.shape[0]} entries but there are {shape[0]} acquisitions"
            )
        n_arr = n_arr.reshape((shape[0],) + (1,) * (len(shape) - 1))
    try:
        n_arr = np.broadcast_to(n_arr, shape)
    except ValueError:
        raise OptionError(
            f"n has shape {np.shape(n)}; expected a scalar, (A,) = ({shape[0]},) or {shape}"
        ) from None
    for name, arr in (("mean", mean), ("var", var), ("n", n_arr), *out.items()):
        if not np.all(np.isfinite(arr)):
            raise OptionError(f"{name} contains NaN or infinite values")
    if np.any(n_arr < 2):
        raise OptionError("n (frames per acquisition) must be at least 2")
    if np.any(out["read_noise"] < 0):
        raise OptionError("read_noise must be non-negative (ADU)")
    if np.any(var <= 0):
        bad = np.argwhere(var <= 0)[0]
        raise OptionError(
            f"var must be positive; {np.count_nonzero(var <= 0)} value(s) are not, "
            f"first at index {tuple(int(i) for i in bad)}"
        )
    x = mean - out["offset"]
    if np.any(x <= 0):
        bad = np.argwhere(x <= 0)[0]
        raise OptionError(
            "non-positive signal: mean <= offset in "
            f"{np.count_nonzero(x <= 0)} value(s), first at index "
            f"{tuple(int(i) for i in bad)} (acquisition, pixel...)"
        )
    pn = np.broadcast_to(np.asarray(poisson_normal).reshape((-1,) + (1,) * (len(shape) - 1)), shape)
    read_var = adc.count_variance(out["read_noise"], pn)
    return x, var - read_var, read_var, n_arr, var


# --------------------------------------------------------------------------------------
# The straight-line fit with error propagation
# --------------------------------------------------------------------------------------
class _Line(NamedTuple):
    beta: np.ndarray  # slope, (...)
    dbeta_dx: np.ndarray  # (A, ...)
    dbeta_dy: np.ndarray  # (A, ...)
    var_x: np.ndarray  # sampling variance of x, (A, ...)
    var_y: np.ndarray  # sampling variance of y, (A, ...)
    var_beta: np.ndarray  # (...)
    chi2: np.ndarray  # (...)


def _fit_line(x, y, read_var, n, sample_var, *, intercept, weighted, iterations):
    """Fit ``y = β·x`` (or ``a + β·x``) along axis 0, per pixel, with error propagation."""
    if intercept and x.shape[0] < 2:
        raise OptionError("a fit with an intercept needs at least 2 levels per fit")

    def solve(w):
        if intercept:
            sw = w.sum(axis=0)
            xb = (w * x).sum(axis=0) / sw
            yb = (w * y).sum(axis=0) / sw
        else:
            xb = yb = np.zeros(x.shape[1:])
        dx, dy = x - xb, y - yb
        sxx = (w * dx * dx).sum(axis=0)
        beta = (w * dx * dy).sum(axis=0) / sxx
        return beta, yb - beta * xb, dx, dy, sxx

    def sampling(beta, a):
        total = read_var + a + beta * x  # model variance of the counts (ADU²)
        total = np.where(total > 0, total, sample_var)
        return total / n, 2.0 * total**2 / (n - 1)

    # Start: weights from the sample variances (or none), then re-weight at the fitted line.
    var_x, var_y = sample_var / n, 2.0 * sample_var**2 / (n - 1)
    w = 1.0 / var_y if weighted else np.ones_like(x)
    beta, a, dx, dy, sxx = solve(w)
    for _ in range(iterations if weighted else 0):
        var_x, var_y = sampling(beta, a)
        w = 1.0 / (var_y + beta**2 * var_x)
        beta, a, dx, dy, sxx = solve(w)
    var_x, var_y = sampling(beta, a)
    # ∂β/∂y_j = w_j·dx_j / Sxx;  ∂β/∂x_j = w_j·(dy_j − 2β·dx_j) / Sxx  (weights
    # fixed; the centring terms drop out because Σ w·dx = Σ w·dy = 0).
    dbeta_dy = w * dx / sxx
    dbeta_dx = w * (dy - 2.0 * beta * dx) / sxx
    var_beta = (dbeta_dx**2 * var_x + dbeta_dy**2 * var_y).sum(axis=0)
    resid = y - a - beta * x
    chi2 = (resid**2 / (var_y + beta**2 * var_x)).sum(axis=0)
    return _Line(beta, dbeta_dx, dbeta_dy, var_x, var_y, var_beta, chi2)


def _intensity(x, line, scale):
    """E_i = scale·x_i/β and its delta-method variance over all points of the line."""
    beta = line.beta
    E = scale * x / beta
    # ∂E_i/∂x_j = scale·(δ_ij/β − x_i·∂β/∂x_j / β²)
    # ∂E_i/∂y_j = −scale·x_i·∂β/∂y_j / β²
    coef = x / beta**2  # (A, ...) indexed by i
    d_x = -coef[:, None] * line.dbeta_dx[None, :]  # (i, j, ...)
    idx = np.arange(x.shape[0])
    d_x[idx, idx] += 1.0 / beta
    d_y = -coef[:, None] * line.dbeta_dy[None, :]
    var_E = scale**2 * (
        (d_x**2 * line.var_x[None, :]).sum(axis=1) + (d_y**2 * line.var_y[None, :]).sum(axis=1)
    )
    return E, var_E


def _intensity_bounds(x, line, scale):
    """Fieller bounds of E_i = scale·x_i/β (numerator and slope correlated through x_i)."""
    cov_xb = line.dbeta_dx * line.var_x  # Cov(x_i, β) = ∂β/∂x_i · Var(x_i)
    return fieller_interval(
        scale * x, line.beta, scale**2 * line.var_x, line.var_beta, scale * cov_xb
    )


def _positive_or_nan(beta):
    return np.where(beta > 0, beta, np.nan)


def fieller_interval(a, b, var_a, var_b, cov_ab=0.0, *, z=_Z95):
    """Confidence bounds of a positive ratio ``a/b`` by Fieller's theorem.

    The set of ratios R with ``(a − R·b)² ≤ z²·Var(a − R·b)`` — the values of R that a
    normal test of ``a − R·b = 0`` does not reject — intersected with R > 0. Unlike
    ``a/b ± z·SE`` it stays a valid interval when b is poorly determined: it then reaches
    to infinity (b not significantly different from 0), and it exists where ``a/b`` does
    not (b ≤ 0).

    Parameters
    ----------
    a, b : array_like
        Numerator and denominator estimates (any units; the bounds are in those of a/b).
    var_a, var_b, cov_ab : array_like
        Their sampling variances and covariance (broadcast together).
    z : float, optional
        Normal quantile; 1.959964 (the default) gives 95 % bounds.

    Returns
    -------
    lower, upper : ndarray
        The bounds; ``lower`` is 0 and/or ``upper`` is ``inf`` where the confidence set
        reaches there, and both are NaN where it holds no positive ratio.

    Examples
    --------
    >>> from emccdcal.fit.mv import fieller_interval
    >>> lo, hi = fieller_interval(10.0, 2.0, 0.0, 0.01)  # 1/β-type: 10/(2 ± 1.96·0.1)
    >>> round(float(lo), 4), round(float(hi), 4)
    (4.5537, 5.5432)
    >>> lo, hi = fieller_interval(10.0, 0.1, 0.0, 0.01)  # b within 1.96 SE of 0
    >>> round(float(lo), 2), float(hi)  # 10/(0.1 + 1.96·0.1) and beyond
    (33.78, inf)
    """
    a, b, var_a, var_b, cov_ab = np.broadcast_arrays(
        *(np.asarray(v, dtype=float) for v in (a, b, var_a, var_b, cov_ab))
    )
    z2 = z * z
    # (b² − z²V_b)·R² − 2(ab − z²C)·R + (a² − z²V_a) ≤ 0
    qa = b * b - z2 * var_b
    qb = a * b - z2 * cov_ab
    qc = a * a - z2 * var_a
    disc = qb * qb - qa * qc
    root = np.sqrt(np.maximum(disc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        r1, r2 = (qb - root) / qa, (qb + root) / qa
    lo_root, hi_root = np.minimum(r1, r2), np.maximum(r1, r2)
    bounded = qa > 0  # b significantly non-zero: the set is [lo_root, hi_root]
    lower = np.where(bounded, np.maximum(lo_root, 0.0), 0.0)
    upper = np.where(bounded, hi_root, np.inf)
    # Unbounded (qa ≤ 0): the set is (−∞, lo_root] ∪ [hi_root, ∞), or everything when
    # disc < 0; its positive part is [hi_root, ∞) only when lo_root ≤ 0 < hi_root.
    tail = ~bounded & (disc >= 0) & (lo_root <= 0) & (hi_root > 0)
    lower = np.where(tail, hi_root, lower)
    finite = np.isfinite(qa) & np.isfinite(qb) & np.isfinite(qc)
    empty = (bounded & ((disc < 0) | (hi_root <= 0))) | ~finite
    lower = np.where(empty, np.nan, lower)
    upper = np.where(empty, np.nan, upper)
    return lower, upper


# --------------------------------------------------------------------------------------
# Public functions
# --------------------------------------------------------------------------------------
def fit_mv_adu(
    mean,
    var,
    offset,
    read_noise,
    n,
    *,
    intercept: bool = False,
    weighted: bool = True,
    iterations: int = 3,
) -> MVADUFit:
    """ADU conversion factor φ from a 1× intensity series by mean–variance (``mv-adu``).

    Fits ``Var(S) − σ² = (⟨S⟩ − S0)/φ`` per pixel over the ``A`` levels (paper Eq. 5a),
    by weighted least squares through the origin (see the module docstring for the
    choices and what the standard errors include).

    Parameters
    ----------
    mean : array_like, shape ``(A, *pixels)``
        Sample mean of the raw counts of each acquisition (ADU), all at EM gain 1×.
    var : array_like, shape ``(A, *pixels)``
        Unbiased (``ddof=1``) sample variance of the same counts (ADU²).
    offset : array_like, broadcastable to ``(A, *pixels)``
        Dark offset map S0 (ADU); a single ``pixels``-shaped map serves every level.
    read_noise : array_like, broadcastable to ``(A, *pixels)``
        Dark read-noise map σ (ADU).
    n : int or array_like
        Frames per acquisition: a scalar, one per acquisition ``(A,)``, or the full shape.
        Must be ≥ 2.
    intercept : bool, optional
        Fit ``y = a + x/φ`` with a free intercept instead of through the origin (needs
        ≥ 2 levels). Default False.
    weighted : bool, optional
        Weight each level by its inverse effective sampling variance (default True);
        False gives ordinary least squares.
    iterations : int, optional
        Re-weighting passes at the fitted line (default 3; ignored if not weighted).

    Returns
    -------
    MVADUFit
        ``e_per_adu`` φ (e⁻/ADU) and ``e_per_adu_se``, shape ``pixels``;
        ``photoelectrons`` E and ``photoelectrons_se`` (e⁻), shape ``(A, *pixels)``;
        ``chi2``, ``dof``, ``valid``.

    Raises
    ------
    ValueError
        Mismatched shapes, no level, NaN or infinite input, ``n < 2``, ``var ≤ 0``, or a
        non-positive signal (``mean ≤ offset``) anywhere.

    Examples
    --------
    >>> import numpy as np
    >>> from emccdcal.fit.mv import fit_mv_adu
    >>> phi, s0, sigma, n = 3.5, 100.0, 10.0, 5000
    >>> E = np.array([[50.0], [200.0], [800.0]])  # three levels, one pixel
    >>> mean = s0 + E / phi
    >>> var = sigma**2 + E / phi**2  # the noise model's exact moments
    >>> fit = fit_mv_adu(mean, var, s0, sigma, n)
    >>> float(np.round(fit.e_per_adu[0], 6))
    3.5
    >>> np.round(fit.photoelectrons[:, 0], 6).tolist()
    [50.0, 200.0, 800.0]
    """
    x, y, read_var, n_arr, sample_var = _moments(mean, var, offset, read_noise, n)
    line = _fit_line(
        x,
        y,
        read_var,
        n_arr,
        sample_var,
        intercept=intercept,
        weighted=weighted,
        iterations=int(iterations),
    )
    phi_lower, phi_upper = fieller_interval(1.0, line.beta, 0.0, line.var_beta)
    E_lower, E_upper = _intensity_bounds(x, line, 1.0)
    beta = _positive_or_nan(line.beta)
    line = line._replace(beta=beta)
    phi = 1.0 / beta
    phi_se = np.sqrt(line.var_beta) / beta**2
    E, var_E = _intensity(x, line, 1.0)
    E_se = np.sqrt(var_E)
    valid = np.isfinite(phi) & np.isfinite(phi_se) & np.all(np.isfinite(E_se), axis=0)
    dof = x.shape[0] - (2 if intercept else 1)
    return MVADUFit(
        phi, phi_se, E, E_se, line.chi2, dof, valid, phi_lower, phi_upper, E_lower, E_upper
    )


def fit_mv_gain(
    mean,
    var,
    offset,
    read_noise,
    n,
    e_per_adu,
    setpoint,
    *,
    e_per_adu_se=None,
    intercept: bool = False,
    weighted: bool = True,
    iterations: int = 3,
    em_model=None,
) -> MVGainFit:
    """True EM gain per set-point by mean–variance (``mv-gain``), with φ known.

    At gain g the variance above read noise grows as ``2g/φ`` times the offset-subtracted
    mean (paper Eq. 5b, 6). The acquisitions are grouped by set-point:

    * one acquisition at a set-point (a gain series): the single-point estimate
      ``g = φ·(Var − σ²) / (2·(⟨S⟩ − S0))``;
    * several (an intensity series at that gain): the slope of the weighted
      least-squares line through the origin over the levels, ``g = φ·β/2``;
    * set-point 1: no multiplication, ``g = 1`` exactly (SE 0), ``E = (⟨S⟩ − S0)·φ``.

    Parameters
    ----------
    mean, var, offset, read_noise, n
        As in :func:`fit_mv_adu`, for ``A`` acquisitions at any set-points.
    e_per_adu : float or array_like, broadcastable to ``pixels``
        φ (e⁻/ADU), e.g. from :func:`fit_mv_adu` or an IS-MLE fit.
    setpoint : array_like, shape ``(A,)``
        The camera's EM-gain set-point of each acquisition (dimensionless, > 0).
    e_per_adu_se : float or array_like, optional
        Standard error of φ (e⁻/ADU); propagated into the gains' SEs (and into E at 1×).
        Default: φ treated as exact.
    intercept, weighted, iterations
        As in :func:`fit_mv_adu`; an intercept needs ≥ 2 levels at every set-point
        other than 1.
    em_model : emccdcal.model.noise.EMModel, optional
        The register's excess-noise factor F²: 2 for the paper's gamma model (default),
        the exact ``F²(g, N)`` of a Bernoulli cascade of N stages for
        ``EMModel("cascade", N)``. The variance then grows as ``g·F²(g)/φ`` times the
        mean, and g solves ``g·F²(g, N) = φβ``
        (:func:`emccdcal.model.cascade.gain_from_gain_f2`); the F² = 2 estimate is low
        by F²/2 − 1 (−10 % at 5×).

    Returns
    -------
    MVGainFit
        ``setpoints`` (S,), ``em_gain``/``em_gain_se`` (S, *pixels),
        ``photoelectrons``/``photoelectrons_se`` (A, *pixels) in e⁻, ``chi2``, ``dof``,
        ``valid``.

    Raises
    ------
    ValueError
        As :func:`fit_mv_adu`, plus a ``setpoint`` that is not one positive finite number
        per acquisition and a non-positive or non-finite ``e_per_adu``.

    Examples
    --------
    >>> import numpy as np
    >>> from emccdcal.fit.mv import fit_mv_gain
    >>> phi, s0, sigma, E = 3.5, 100.0, 10.0, 40.0
    >>> g = np.array([1.0, 20.0, 150.0])
    >>> mean = (s0 + g * E / phi)[:, None]  # three set-points, one pixel
    >>> F2 = np.where(g == 1, 1.0, 2.0)  # PN at 1×, PGN otherwise
    >>> var = (sigma**2 + F2 * E * (g / phi) ** 2)[:, None]
    >>> fit = fit_mv_gain(mean, var, s0, sigma, 5000, phi, [1, 20, 150])
    >>> np.round(fit.em_gain[:, 0], 6).tolist()
    [1.0, 20.0, 150.0]
    >>> np.round(fit.photoelectrons[:, 0], 6).tolist()
    [40.0, 40.0, 40.0]
    """
    sp = np.asarray(setpoint, dtype=float)
    x, y, read_var, n_arr, sample_var = _moments(mean, var, offset, read_noise, n, sp == 1)
    A, pixels = x.shape[0], x.shape[1:]
    if sp.shape != (A,):
        raise OptionError(
            f"setpoint must have one entry per acquisition, shape ({A},); got {sp.shape}"
        )
    if not np.all(np.isfinite(sp) & (sp > 0)):
        raise OptionError("setpoint values must be positive and finite")
    phi = _pixel_param("e_per_adu", e_per_adu, pixels, positive=True)
    phi_var = (
        np.zeros(pixels)
        if e_per_adu_se is None
        else _pixel_param("e_per_adu_se", e_per_adu_se, pixels) ** 2
    )
    setpoints = np.unique(sp)
    S = setpoints.size
    g = np.empty((S,) + pixels)
    g_se = np.empty((S,) + pixels)
    chi2 = np.zeros((S,) + pixels)
    dof = np.zeros(S, dtype=int)
    E = np.empty_like(x)
    E_se = np.empty_like(x)
    g_lower, g_upper = np.full_like(g, np.nan), np.full_like(g, np.nan)
    E_lower, E_upper = np.empty_like(x), np.empty_like(x)
    for k, s in enumerate(setpoints):  # a loop over set-points, not pixels
        rows = np.flatnonzero(sp == s)
        xs = x[rows]
        if s == 1.0:
            g[k], g_se[k] = 1.0, 0.0
            E[rows] = xs * phi
            var_x = sample_var[rows] / n_arr[rows]
            E_se[rows] = np.sqrt(phi**2 * var_x + xs**2 * phi_var)
            # E = x·φ: a product of two well-determined numbers, a Wald interval
            E_lower[rows] = np.maximum(E[rows] - _Z95 * E_se[rows], 0.0)
            E_upper[rows] = E[rows] + _Z95 * E_se[rows]
            continue
        line = _fit_line(
            xs,
            y[rows],
            read_var[rows],
            n_arr[rows],
            sample_var[rows],
            intercept=intercept,
            weighted=weighted,
            iterations=int(iterations),
        )
        # g = β/(2/φ): the slope's interval scaled, widened by φ's error if given
        g_lower[k], g_upper[k] = fieller_interval(
            line.beta, 2.0 / phi, line.var_beta, 4.0 * phi_var / phi**4
        )
        E_lower[rows], E_upper[rows] = _intensity_bounds(xs, line, 2.0)
        beta = _positive_or_nan(line.beta)
        line = line._replace(beta=beta)
        g[k] = phi * beta / 2.0
        g_se[k] = np.sqrt((phi / 2.0) ** 2 * line.var_beta + (beta / 2.0) ** 2 * phi_var)
        E_k, var_E = _intensity(xs, line, 2.0)
        E[rows], E_se[rows] = E_k, np.sqrt(var_E)
        chi2[k] = line.chi2
        dof[k] = rows.size - (2 if intercept else 1)
        if em_model is not None:
            # g solves g·F²(g) = φβ under the register's excess-noise factor (the
            # gamma model's F² = 2 above); E = ⟨S − S0⟩·φ/g moves with it.
            g_gamma = g[k].copy()
            solve = em_model.register.gain_from_gain_f2
            g[k], slope = solve(2.0 * g_gamma)
            g_se[k] = g_se[k] * 2.0 / slope  # dg/d(φβ) = 1/(d(g F²)/dg)
            g_lower[k] = solve(2.0 * g_lower[k])[0]
            g_upper[k] = solve(2.0 * g_upper[k])[0]
            # (where the gain is not estimable E keeps its photon-transfer interval)
            same = (g[k] == g_gamma) | (np.isnan(g[k]) & np.isnan(g_gamma))
            with np.errstate(invalid="ignore", divide="ignore"):
                ratio = np.where(same, 1.0, g_gamma / g[k])
            E[rows], E_se[rows] = E[rows] * ratio, E_se[rows] * ratio
            E_lower[rows], E_upper[rows] = E_lower[rows] * ratio, E_upper[rows] * ratio
    valid = np.all(np.isfinite(g) & np.isfinite(g_se), axis=0) & np.all(
        np.isfinite(E) & np.isfinite(E_se), axis=0
    )
    return MVGainFit(
        setpoints, g, g_se, E, E_se, chi2, dof, valid, g_lower, g_upper, E_lower, E_upper
    )


def mean_ratio_gains(mean, var, offset, n, setpoint) -> MeanRatioGains:
    """Gains relative to the 1× acquisition from the ratio of offset-subtracted means.

    ``g_i = (⟨S_i⟩ − S0_i) / (⟨S_1⟩ − S0_1)``, where acquisition 1 is the one at
    set-point 1. This assumes the illumination (E) is the same in every acquisition, as in a gain
    series; it does not depend on φ or on the excess-noise factor, so it is free of the
    F² bias of :func:`fit_mv_gain` at low gain (docs/simulation.md) and is a good starting value
    for the likelihood fits.

    Parameters
    ----------
    mean : array_like, shape ``(A, *pixels)``
        Sample mean of the raw counts per acquisition (ADU).
    var : array_like, shape ``(A, *pixels)``
        Sample variance of the counts (ADU²), for the standard errors.
    offset : array_like, broadcastable to ``(A, *pixels)``
        Dark offset map S0 of each acquisition (ADU).
    n : int or array_like
        Frames per acquisition (scalar, ``(A,)`` or full shape), ≥ 2.
    setpoint : array_like, shape ``(A,)``
        EM-gain set-point of each acquisition; exactly one must be 1.

    Returns
    -------
    MeanRatioGains
        ``em_gain`` and ``em_gain_se``, shape ``(A, *pixels)``, dimensionless. The SE
        comes from the sampling variance of both means (``var/n``); it does not include
        the dark offsets' uncertainty or any drift of the illumination.

    Raises
    ------
    ValueError
        As :func:`fit_mv_adu`, or not exactly one acquisition at set-point 1.

    Examples
    --------
    >>> import numpy as np
    >>> from emccdcal.fit.mv import mean_ratio_gains
    >>> mean = np.array([[110.0], [150.0], [600.0]])
    >>> r = mean_ratio_gains(mean, np.full((3, 1), 200.0), 100.0, 5000, [1, 5, 50])
    >>> r.em_gain[:, 0].tolist()
    [1.0, 5.0, 50.0]
    """
    x, _, _, n_arr, sample_var = _moments(mean, var, offset, 0.0, n)
    A = x.shape[0]
    sp = np.asarray(setpoint, dtype=float)
    if sp.shape != (A,):
        raise OptionError(
            f"setpoint must have one entry per acquisition, shape ({A},); got {sp.shape}"
        )
    ref = np.flatnonzero(sp == 1.0)
    if ref.size != 1:
        raise OptionError(
            f"mean-ratio gains need exactly one acquisition at set-point 1; found {ref.size}"
        )
    r = int(ref[0])
    g = x / x[r]
    rel_var = sample_var / (n_arr * x**2)  # Var(x_i)/x_i²
    g_se = np.abs(g) * np.sqrt(rel_var + rel_var[r])
    g[r], g_se[r] = 1.0, 0.0
    return MeanRatioGains(g, g_se)


def _pixel_param(name, value, pixels, *, positive=False):
    arr = np.asarray(value, dtype=float)
    try:
        arr = np.broadcast_to(arr, pixels)
    except ValueError:
        raise OptionError(
            f"{name} has shape {arr.shape}, which does not broadcast to the pixel shape {pixels}"
        ) from None
    if not np.all(np.isfinite(arr)):
        raise OptionError(f"{name} contains NaN or infinite values")
    if positive and np.any(arr <= 0):
        raise OptionError(f"{name} must be positive")
    if not positive and np.any(arr < 0):
        raise OptionError(f"{name} must be non-negative")
    return arr


def photon_transfer_e_per_adu(frames, offset, read_noise, *, dark_frames=None):
    """φ (e⁻/ADU) that the photon transfer of an unmultiplied (1×) stack implies, pooled
    over its pixels, with its relative standard error: a check of a φ given from
    elsewhere, not an estimate to calibrate with (``is-adu`` and ``mv-adu`` are those).

    φ̂ = Σ(mean − offset) / Σ(var − read_noise²) over the pixels. Its standard error by
    the delta method: the means' sampling variance var/n, the variances' 2v²/(n − 1),
    and, with ``dark_frames``, the maps' own (σ²/n_dark for an offset, 2σ⁴/n_dark for a
    variance). A drift of the light inflates the variance and reads φ low (the
    data-quality checks look for one); the variance of successive differences would not,
    but the real ProEM frames' small negative frame-to-frame correlation (−1 %) reads it
    15 % low there.

    Parameters
    ----------
    frames : ndarray, shape (frames, ...)
        Raw counts (ADU) of a 1× acquisition (at least 8 frames).
    offset, read_noise : ndarray, shape (...)
        The maps (ADU).
    dark_frames : int, optional
        Frames behind the maps; None takes them as exact.

    Returns
    -------
    (float, float)
        φ̂ (e⁻/ADU) and its relative SE; (nan, inf) where the stack holds too little
        light above its read noise to tell.
    """
    x = np.asarray(frames, dtype=np.float64)
    n = x.shape[0]
    if n < 8:
        return math.nan, math.inf
    mean = x.mean(axis=0)
    v = x.var(axis=0, ddof=1)
    s2 = np.asarray(read_noise, dtype=np.float64) ** 2
    a = float(np.sum(mean - offset))
    b = float(np.sum(v - s2))
    var_a = float(np.sum(v / n))
    var_b = float(np.sum(2 * v**2 / (n - 1)))
    if dark_frames:
        var_a += float(np.sum(s2 / dark_frames))
        var_b += float(np.sum(2 * s2**2 / dark_frames))
    if not (a > 0 and b > 0):
        return math.nan, math.inf
    return a / b, math.sqrt(var_a / a**2 + var_b / b**2)
