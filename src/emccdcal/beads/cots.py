"""Calibration-on-the-spot (COTS): the EM gain and offset from the frames of one bead.

COTS (Mortensen & Flyvbjerg, *Sci. Rep.* 6, 28680, 2016) reads the system
gain G (ADU per photoelectron, "counts per photoelectron") and the offset S0 (ADU) from
how the frame-to-frame variance of a spot's pixels grows with their expected signal. For
every frame of one isolated spot:

1. **Gaussian-mask estimate.** An unweighted least-squares fit of ``E_i = N·P_i + b`` to
   the raw counts of the ROI (:func:`gaussian_mask_fit`): ``P_i`` the pixel-integrated
   Gaussian of :mod:`emccdcal.model.psf`, N the spot total and b the background *plus offset*
   (both ADU). Width, N and b are fitted as square roots (they stay positive). A frame
   whose centre lands more than one pixel from the ROI centre has its ROI moved by the
   rounded offset and is refitted (at most :data:`MAX_RECENTRE` times).
2. **Hat matrix.** ``f = J (JᵀJ)⁻¹ Jᵀ`` with J the exact Jacobian of the fit.
3. **Variance model.** ``v_i = 2·G·(E_i − S0)`` (excess-noise factor 2, no read noise),
   fitted by minimising ``Σ_i [ln v_i + (S_i − E_i)²/v_i]`` over (G, H = G·S0)
   (:func:`fit_variance_model`, Fisher scoring vectorised over frames).
4. **Bias and covariance.** The bias of (G, H) from E_i having been fitted to the same
   counts (first order in 1/pixels, from f), plus the small-sample bias of the variance
   fit itself, and the sandwich covariance, from f and the register's own cumulants with
   the read noise taken out of them (:func:`variance_bias_covariance`; derivation in
   ``docs/cots.md``). Evaluated at the bias-corrected frame average, not at each frame's
   own (±30 %) estimate; frames whose G fits at or below zero are part of that average.
5. **Average over frames.** ``G = mean_f(G_f − ΔG_f)`` with ``Var = mean_f(var G_f)/n``,
   ``S0 = mean_f(H_f − ΔH_f)/G`` with its delta-method variance (:func:`cots_spot`).

This module holds the numerics of one spot; :mod:`emccdcal.beads.cots_calibration` runs
them on every bead of a manifest. ``docs/cots.md`` has the assumptions and measured figures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import defaults
from .._optimize import maximize
from ..errors import OptionError
from ..model import psf
from .cots_bias import (
    GAMMA_CUMULANTS,
    _thin_q,
    _hat_moments,
    _pseudo_true,
    _covariance,
    register_cumulants,
    variance_bias_covariance,
    _CHUNK,
)

__all__ = [
    "MIN_FRAMES",
    "MAX_RECENTRE",
    "SpotFit",
    "CotsSpot",
    "gaussian_mask_fit",
    "hat_matrix",
    "fit_variance_model",
    "variance_bias_covariance",
    "register_cumulants",
    "GAMMA_CUMULANTS",
    "cots_spot",
    "DEFAULT_HALF_SIZE",
    "DEFAULT_WIDTH",
]

#: Fewest frames of a spot COTS accepts (its SE is an average over frames).
MIN_FRAMES = 10
#: Most times one frame's ROI is moved to follow its spot.
MAX_RECENTRE = 20
#: Default ROI half-width Δ (pixel) of :func:`~emccdcal.beads.cots_calibration.cots_calibrate`: (2Δ + 1)² pixels per bead.
DEFAULT_HALF_SIZE = defaults.BEAD_HALF_SIZE
#: Default initial PSF standard deviation (pixel): the bead fits' (``validate``) too.
DEFAULT_WIDTH = psf.DEFAULT_WIDTH
#: Fraction of a spot's frames that must give a usable estimate.
_MIN_USABLE = 0.5


# --------------------------------------------------------------------------------------
# 1. Gaussian-mask estimate (unweighted least squares), vectorised over frames
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SpotFit:
    """Per-frame Gaussian-mask fits of one spot.

    Attributes
    ----------
    params : ndarray, shape (F, 5)
        x, y (pixel, from the ROI centre; x along columns), width s (pixel), spot total N
        and background b (both ADU; b includes the offset), in :data:`psf.PARAMETERS` order.
    expected : ndarray, shape (F, h, w)
        Fitted expected counts E_i (ADU).
    jacobian : ndarray, shape (F, h, w, 5)
        ∂E_i/∂params at the fit (ADU per parameter unit).
    converged : ndarray of bool, shape (F,)
        The fit converged to finite values.
    """

    params: np.ndarray
    expected: np.ndarray
    jacobian: np.ndarray
    converged: np.ndarray


def _coords(n: int) -> np.ndarray:
    """Pixel-centre coordinates from the ROI centre: −(n−1)/2 … (n−1)/2."""
    return np.arange(n) - (n - 1) / 2.0


def _initial_params(roi: np.ndarray, width: float) -> np.ndarray:
    """Moment-based starting values per frame: background from the ROI border."""
    F, h, w = roi.shape
    border = np.concatenate(
        [roi[:, 0, :], roi[:, -1, :], roi[:, 1:-1, 0], roi[:, 1:-1, -1]], axis=1
    )
    b = np.median(border, axis=1)
    excess = np.clip(roi - b[:, None, None], 0, None)
    total = excess.sum(axis=(1, 2))
    safe = np.where(total > 0, total, 1.0)
    rows, cols = _coords(h), _coords(w)
    y = np.where(total > 0, (excess.sum(axis=2) * rows).sum(axis=1) / safe, 0.0)
    x = np.where(total > 0, (excess.sum(axis=1) * cols).sum(axis=1) / safe, 0.0)
    x = np.clip(x, -1.0, 1.0)
    y = np.clip(y, -1.0, 1.0)
    n = np.maximum(total, 1.0)
    return np.stack([x, y, np.full(F, float(width)), n, np.maximum(b, 1e-3)], axis=1)


def _to_q(params: np.ndarray) -> np.ndarray:
    q = params.copy()
    q[:, 2:] = np.sqrt(params[:, 2:])
    return q


def _to_params(q: np.ndarray) -> np.ndarray:
    p = q.copy()
    p[:, 2:] = q[:, 2:] ** 2
    return p


def gaussian_mask_fit(roi, *, width=DEFAULT_WIDTH, init=None, max_iter=200, tol=1e-12):
    """Unweighted least-squares fit of a pixel-integrated Gaussian spot to every frame.

    The Gaussian-mask estimator of COTS (Mortensen & Flyvbjerg 2016, step 1): minimises
    ``Σ_i (S_i − N·P_i(x, y, s) − b)²`` per frame by Levenberg–Marquardt, vectorised over
    frames, in the parameters (x, y, √s, √N, √b) so that s, N and b stay positive.

    Parameters
    ----------
    roi : array_like, shape (F, h, w)
        Raw counts of the ROI in every frame (ADU; not offset-subtracted).
    width : float
        Initial PSF standard deviation s (pixel).
    init : array_like, shape (F, 5) or (5,), optional
        Starting values (x, y, s, N, b) with x, y from the ROI centre (pixel) and N, b in
        ADU; default from the frame's moments and border median.
    max_iter : int
        Most Levenberg–Marquardt iterations.
    tol : float
        Stop when the next step promises to lower the residual sum of squares by less
        than this fraction of it.

    Returns
    -------
    SpotFit
    """
    data = np.asarray(roi, dtype=float)
    if data.ndim != 3 or min(data.shape[1:]) < 3:
        raise OptionError(
            f"gaussian_mask_fit needs a (frames, h, w) stack with h, w >= 3, got shape {data.shape}"
        )
    F, h, w = data.shape
    rows, cols = _coords(h), _coords(w)
    if init is None:
        p0 = _initial_params(data, width)
    else:
        p0 = np.broadcast_to(np.asarray(init, float), (F, 5)).copy()
        p0[:, 2:] = np.maximum(p0[:, 2:], 1e-6)
    q = _to_q(p0)
    flat = data.reshape(F, -1)

    def model(qq, jac):
        p = _to_params(qq)
        if not jac:
            return psf.spot_image(p, rows, cols).reshape(len(qq), -1)
        e, j = psf.spot_image(p, rows, cols, jacobian=True)
        j = j.reshape(len(qq), -1, 5).copy()
        j[:, :, 2:] *= 2.0 * qq[:, None, 2:]  # dθ/dq = 2q for the square-rooted ones
        return e.reshape(len(qq), -1), j

    def evaluate(idx, qq):  # −½ SSR, its gradient Jᵀr and Gauss–Newton's JᵀJ
        e, j = model(qq, True)
        r = flat[idx] - e
        return (
            -0.5 * np.sum(r * r, axis=1),
            np.einsum("fni,fn->fi", j, r),
            np.einsum("fni,fnk->fik", j, j),
        )

    unbounded = np.full(5, np.inf)
    opt = maximize(
        evaluate,
        q,
        lower=-unbounded,
        upper=unbounded,
        tol=0.0,
        rtol=tol,
        max_iter=max_iter,
        max_step=np.inf,
        accept_rtol=0.0,
    )
    q, ssr, done = opt.x, -2.0 * opt.objective, opt.done
    params = _to_params(q)
    e, jac = psf.spot_image(params, rows, cols, jacobian=True)
    converged = done & np.all(np.isfinite(params), axis=1) & (params[:, 2] > 0) & np.isfinite(ssr)
    return SpotFit(params=params, expected=e, jacobian=jac, converged=converged)


def hat_matrix(jacobian) -> np.ndarray:
    """The hat ("transfer") matrix ``f = J (JᵀJ)⁻¹ Jᵀ`` of a least-squares fit, per frame.

    Parameters
    ----------
    jacobian : array_like, shape (F, n, p) or (F, h, w, p)
        ∂E_i/∂θ of the n pixels by the p fitted parameters.

    Returns
    -------
    ndarray, shape (F, n, n)
        The orthogonal projection onto the columns of J (symmetric, trace p): the fitted
        values respond to the data as ``δE = f·δS``. Invariant to reparametrisation.
    """
    qm = _thin_q(jacobian)
    return qm @ np.swapaxes(qm, 1, 2)


# --------------------------------------------------------------------------------------
# 2. The variance model v_i = 2 (G E_i − H), H = G·S0, vectorised over frames
# --------------------------------------------------------------------------------------
def _objective(alpha, r2, expected):
    v = 2.0 * (alpha[:, :1] * expected - alpha[:, 1:])
    with np.errstate(divide="ignore", invalid="ignore"):
        obj = np.sum(np.log(v) + r2 / v, axis=1)
    obj[~np.all(v > 0, axis=1) | ~np.isfinite(obj)] = np.inf
    return obj, v


def _start(r2, expected, leverage, gain0, offset0):
    """Starting (G, H) per frame: a pooled moment regression, kept inside v > 0."""
    F = len(r2)
    emin = expected.min(axis=1)
    g_est = s0_est = np.nan
    if gain0 is None or offset0 is None:
        # E r_i² ≈ (1 − f_ii) v_i: regress r²/(1 − f_ii) on E over all frames and pixels.
        lev = np.clip(leverage, 0.0, 0.9)
        slope, icept = np.polyfit(expected.ravel(), (r2 / (1.0 - lev)).ravel(), 1)
        g_est = slope / 2.0
        s0_est = -icept / slope if slope > 0 else np.nan
    g = float(gain0) if gain0 is not None else g_est
    s0 = float(offset0) if offset0 is not None else s0_est
    if not (np.isfinite(g) and g > 0):
        g = np.nan  # the variance does not grow with the signal: nothing to fit
    spread = np.median(expected, axis=1) - emin
    s0_f = np.where(np.isfinite(s0) & (s0 < emin - 0.05 * spread), s0, emin - 0.5 * spread)
    return np.stack([np.full(F, g), g * s0_f], axis=1)


def fit_variance_model(
    counts, expected, *, leverage=None, gain0=None, offset0=None, max_iter=100, tol=1e-12
):
    """Fit COTS's variance model to every frame: ``v_i = 2·G·(E_i − S0)``.

    Minimises ``L(G, H) = Σ_i [ln v_i + (S_i − E_i)²/v_i]`` with ``v_i = 2 (G·E_i − H)``
    (H = G·S0; the Gaussian approximation of the pixel likelihood, docs/cots.md;
    Mortensen & Flyvbjerg 2016 step 4) by damped Fisher scoring, vectorised over frames.
    L is the objective of the Nelder–Mead search of the COTS software; any optimiser
    finds the same minimum.

    Parameters
    ----------
    counts : array_like, shape (F, n) or (F, h, w)
        Raw counts S_i (ADU).
    expected : array_like, same shape
        Fitted expected counts E_i (ADU; they include the offset).
    leverage : array_like, shape (F, n), optional
        Diagonals f_ii of the hat matrices, for the pooled starting values only.
    gain0, offset0 : float, optional
        Starting G (ADU/e⁻) and S0 (ADU); default from a pooled moment regression.
    max_iter : int
        Most Fisher-scoring iterations.
    tol : float
        Stop when the Newton decrement ``∇ᵀI⁻¹∇`` (the fall of L still to come, ×2) is
        below this.

    Returns
    -------
    alpha : ndarray, shape (F, 2)
        (G, H) per frame: G in ADU/e⁻, H = G·S0 in ADU²/e⁻. Not bias-corrected.
    converged : ndarray of bool, shape (F,)
    """
    s = np.asarray(counts, float).reshape(len(counts), -1)
    e = np.asarray(expected, float).reshape(len(expected), -1)
    r2 = (s - e) ** 2
    lev = np.zeros_like(e) if leverage is None else np.asarray(leverage, float)
    alpha = _start(r2, e, lev, gain0, offset0)

    def evaluate(idx, a):  # −L, its gradient and the expected information (Fisher scoring)
        obj, v = _objective(a, r2[idx], e[idx])
        ei = e[idx]
        h0 = 1.0 / v - r2[idx] / v**2
        grad = -np.stack([np.sum(h0 * 2 * ei, axis=1), np.sum(h0 * -2.0, axis=1)], axis=1)
        w = 1.0 / v**2
        fish = np.empty((len(idx), 2, 2))  # always positive definite
        fish[:, 0, 0] = np.sum(w * 4 * ei**2, axis=1)
        fish[:, 0, 1] = fish[:, 1, 0] = np.sum(w * -4 * ei, axis=1)
        fish[:, 1, 1] = np.sum(w * 4.0, axis=1)
        return -obj, grad, fish

    unbounded = np.full(2, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):  # trials outside v > 0
        opt = maximize(
            evaluate,
            alpha,
            lower=-unbounded,
            upper=unbounded,
            tol=0.5 * tol,
            max_iter=max_iter,
            max_step=np.inf,
        )
    alpha, obj, conv = opt.x, -opt.objective, opt.done
    # G ≤ 0 is a frame's noisy estimate, not a failure: leaving such frames out biases the
    # average up (+4 % at 5× with read noise dominating; docs/cots.md)
    conv &= np.all(np.isfinite(alpha), axis=1) & np.isfinite(obj)
    return alpha, conv


# --------------------------------------------------------------------------------------
# 4. One spot: all of it, and the average over frames
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CotsSpot:
    """COTS on one spot: per-frame estimates and their average.

    Attributes
    ----------
    gain, gain_se : float
        G, the system gain in ADU per photoelectron ("counts per photoelectron"), and its
        standard error ``sqrt(mean_f(var G_f)/n_used)``.
    offset, offset_se : float
        S0 (ADU) and its delta-method standard error.
    gain_offset_cov : float
        Cov(G, S0) (ADU²/e⁻).
    gain_scatter_se, offset_scatter_se : float
        The same standard errors from the scatter of the per-frame estimates over frames
        (SD/sqrt(n_used); delta method for S0): a check of the analytic ones.
    n_frames, n_used : int
        Frames given, and frames whose fits were usable.
    n_saturated : int
        Frames left out for a saturated pixel (with ``adc_max``).
    width : float
        Mean fitted PSF standard deviation (pixel).
    spot_counts : float
        Mean fitted spot total N (ADU above the background); ``spot_counts / gain`` is the
        spot's photoelectrons per frame.
    mean_counts : ndarray, shape (h, w)
        Mean raw counts of the initial ROI over the usable frames (ADU).
    mean_counts_se : ndarray, shape (h, w)
        Their standard errors (ADU).
    frame_gain, frame_gain_offset : ndarray, shape (F,)
        Bias-corrected per-frame G_f and H_f = (G·S0)_f (NaN where unusable).
    frame_bias : ndarray, shape (F, 2)
        The subtracted first-order bias of (G_f, H_f).
    frame_cov : ndarray, shape (F, 2, 2)
        Covariance of (G_f, H_f).
    frame_params : ndarray, shape (F, 5)
        Gaussian-mask fits (x, y from the *final* ROI centre of each frame, pixel).
    frame_shift : ndarray of int, shape (F, 2)
        (row, col) by which each frame's ROI was moved from the initial one.
    usable : ndarray of bool, shape (F,)
    """

    gain: float
    gain_se: float
    offset: float
    offset_se: float
    gain_offset_cov: float
    gain_scatter_se: float
    offset_scatter_se: float
    n_frames: int
    n_used: int
    n_saturated: int
    width: float
    spot_counts: float
    mean_counts: np.ndarray
    mean_counts_se: np.ndarray
    frame_gain: np.ndarray
    frame_gain_offset: np.ndarray
    frame_bias: np.ndarray
    frame_cov: np.ndarray
    frame_params: np.ndarray
    frame_shift: np.ndarray
    usable: np.ndarray


def _extract(stack, top, left, h, w):
    """Per-frame ROI of (h, w) pixels at corners (top, left) (arrays of shape (F,))."""
    f = np.arange(stack.shape[0])[:, None, None]
    r = top[:, None, None] + np.arange(h)[None, :, None]
    c = left[:, None, None] + np.arange(w)[None, None, :]
    return stack[f, r, c]


def _recentred_fit(stack, roi, width, init):
    """GME with ROIs that follow the spot (at most MAX_RECENTRE moves per frame).

    A frame whose ROI would have to leave ``stack`` keeps its fit if the spot's centre is
    still inside the ROI; a frame still off-centre after the last move is dropped.
    """
    top0, left0, h, w = roi
    F, R, C = stack.shape
    top = np.full(F, top0, dtype=np.int64)
    left = np.full(F, left0, dtype=np.int64)
    data = _extract(stack, top, left, h, w)
    fit = gaussian_mask_fit(data, width=width, init=init)
    params, expected, jac, conv = (
        fit.params.copy(),
        fit.expected.copy(),
        fit.jacobian.copy(),
        fit.converged.copy(),
    )
    lost = np.zeros(F, bool)
    for _ in range(MAX_RECENTRE):
        move = conv & ~lost & np.any(np.abs(params[:, :2]) > 1.0, axis=1)
        if not move.any():
            break
        idx = np.flatnonzero(move)
        dcol = np.rint(params[idx, 0]).astype(np.int64)
        drow = np.rint(params[idx, 1]).astype(np.int64)
        nt, nl = top[idx] + drow, left[idx] + dcol
        inside = (nt >= 0) & (nl >= 0) & (nt + h <= R) & (nl + w <= C)
        lost[idx[~inside]] = True  # cannot follow: keep the fit (checked below)
        idx, drow, dcol, nt, nl = idx[inside], drow[inside], dcol[inside], nt[inside], nl[inside]
        if idx.size == 0:
            break
        top[idx], left[idx] = nt, nl
        start = params[idx].copy()
        start[:, 0] -= dcol
        start[:, 1] -= drow
        sub = stack[idx]
        refit = gaussian_mask_fit(_extract(sub, nt, nl, h, w), width=width, init=start)
        params[idx], expected[idx] = refit.params, refit.expected
        jac[idx], conv[idx] = refit.jacobian, refit.converged
    half = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    off = np.where(
        lost,
        np.any(np.abs(params[:, :2]) > half, axis=1),
        np.any(np.abs(params[:, :2]) > 1.0, axis=1),
    )
    data = _extract(stack, top, left, h, w)
    shift = np.stack([top - top0, left - left0], axis=1)
    return data, SpotFit(params, expected, jac, conv & ~off), shift


def _spot_inputs(stack, roi, register, e_per_adu, read_noise):
    """:func:`cots_spot`'s inputs checked: the stack as float, the ROI as (top, left,
    rows, cols) and the read-noise map (ADU) of the frames' shape."""
    stack = np.asarray(stack)
    if stack.ndim != 3:
        raise OptionError(f"COTS needs a (frames, rows, cols) stack, got shape {stack.shape}")
    F, R, C = stack.shape
    if F < MIN_FRAMES:
        raise OptionError(f"COTS needs at least {MIN_FRAMES} frames of the spot, got {F}")
    top, left, h, w = (0, 0, R, C) if roi is None else (int(v) for v in roi)
    if top < 0 or left < 0 or top + h > R or left + w > C or min(h, w) < 3:
        raise OptionError(
            f"ROI (top {top}, left {left}, {h}×{w}) does not fit in the "
            f"{R}×{C} frames (or is smaller than 3×3)"
        )
    if register is not None and not (e_per_adu is not None and e_per_adu > 0):
        raise OptionError("COTS: a register model needs e_per_adu (e-/ADU) to know its gain")
    noise_map = np.broadcast_to(np.asarray(read_noise, float), (R, C))
    if not np.all(np.isfinite(noise_map) & (noise_map >= 0)):
        raise OptionError("COTS: read_noise must be finite and >= 0 (ADU)")
    return stack.astype(float, copy=False), (top, left, h, w), noise_map


def cots_spot(
    stack,
    *,
    roi=None,
    width=DEFAULT_WIDTH,
    init=None,
    gain0=None,
    offset0=None,
    exclude=None,
    adc_max=None,
    read_noise=0.0,
    register=None,
    e_per_adu=None,
):
    """Calibration-on-the-spot on the frames of one isolated spot.

    Parameters
    ----------
    stack : array_like, shape (F, R, C)
        Raw counts (ADU, not offset-subtracted) of the frames: the ROI itself, or a larger
        region holding it (then the ROI can follow a moving spot).
    roi : tuple of int (top, left, h, w), optional
        The initial ROI inside ``stack`` (pixel); default the whole of it.
    width : float
        Initial PSF standard deviation (pixel).
    init : array_like, shape (5,) or (F, 5), optional
        Initial (x, y, s, N, b) of the spot fit: x, y from the ROI centre (pixel), s in
        pixels, N and b in ADU. Default from each frame's moments.
    gain0, offset0 : float, optional
        Initial G (ADU/e⁻) and S0 (ADU) of the variance fit; default from a pooled
        moment regression.
    exclude : array_like of bool, shape (F,), optional
        Frames to leave out.
    adc_max : int, optional
        ADC maximum (ADU): frames with a pixel of their ROI at or above it are left out
        (COTS assumes no saturation). Default: no check.
    read_noise : float or array_like of shape (R, C)
        Read-noise SD σ (ADU) of the pixels of ``stack``, e.g. from the darks: the bias
        correction's third and fourth cumulants are the register's alone, which read
        noise dilutes. 0 (COTS as published) overstates them where read noise dominates
        the variance (about −0.4 % of G at 5× with σ = 15.5 ADU; docs/cots.md).
    register : a register of :mod:`emccdcal.model.noise`, optional
        The EM register whose cumulants the bias correction uses
        (:func:`register_cumulants`, at the uncorrected G); default the gamma register's.
    e_per_adu : float, optional
        φ (e⁻/ADU), needed with ``register`` to know its gain.

    Returns
    -------
    CotsSpot

    Raises
    ------
    ValueError
        Fewer than :data:`MIN_FRAMES` frames, an ROI outside the stack, or too few frames
        (< half) with a usable fit.

    Examples
    --------
    >>> from emccdcal.model import psf
    >>> from emccdcal.simulate.camera import simulate_frames
    >>> c = np.arange(10) - 4.5
    >>> spot = psf.spot_image([0.2, -0.1, 1.3, 5000.0, 20.0], c, c)  # photoelectrons
    >>> s = simulate_frames(spot, em_gain=5.0, e_per_adu=1.0, offset=100.0,
    ...                              read_noise=0.01, frames=100, seed=3)
    >>> r = cots_spot(s)
    >>> bool(abs(r.gain - 5.0) < 4 * r.gain_se), bool(abs(r.offset - 100.0) < 4 * r.offset_se)
    (True, True)
    """
    stack, (top, left, h, w), noise_map = _spot_inputs(stack, roi, register, e_per_adu, read_noise)
    F, R, C = stack.shape
    data, fit, shift = _recentred_fit(stack, (top, left, h, w), width, init)
    usable = fit.converged.copy()
    if exclude is not None:
        usable &= ~np.asarray(exclude, bool)
    saturated = np.zeros(F, bool)
    if adc_max is not None:
        saturated = np.any(data >= adc_max, axis=(1, 2))
        usable &= ~saturated
    n = h * w
    counts = data.reshape(F, n)
    expected = fit.expected.reshape(F, n)
    jac = fit.jacobian.reshape(F, n, 5)

    def need(idx, what):
        if idx.size < max(2, _MIN_USABLE * F):
            raise OptionError(
                f"COTS: only {idx.size} of {F} frames gave a usable {what} (need at least "
                "half); is there one isolated spot in the ROI?"
            )

    idx = np.flatnonzero(usable)
    need(idx, "fit of the spot")
    read_var = _extract(
        np.broadcast_to(noise_map**2, (F, R, C)), top + shift[:, 0], left + shift[:, 1], h, w
    ).reshape(F, n)  # follows the ROI
    mom, leverage = _frame_hat_moments(expected, jac, idx, read_var)
    alpha = np.full((F, 2), np.nan)
    a, ok = fit_variance_model(
        counts[idx], expected[idx], leverage=leverage[idx], gain0=gain0, offset0=offset0
    )
    alpha[idx] = a
    usable[idx[~ok]] = False
    cumulants = (
        GAMMA_CUMULANTS
        if register is None or not ok.any()
        else register_cumulants(register, np.mean(a[ok, 0]), e_per_adu)
    )
    a_c, d_inv, fit_point = _corrected_truth(alpha, usable, mom, expected, need, cumulants)
    idx = np.flatnonzero(usable)
    truth = np.tile(a_c, (idx.size, 1))
    bias = np.full((F, 2), np.nan)
    bias[idx] = fit_point - truth
    cov = np.full((F, 2, 2), np.nan)
    for lo in range(0, idx.size, _CHUNK):
        ch = slice(lo, lo + _CHUNK)
        raw_cov = _covariance(
            expected[idx][ch],
            _thin_q(jac[idx[ch]]),
            truth[ch],
            fit_point[ch],
            read_var[idx[ch]],
            cumulants,
        )
        cov[idx[ch]] = d_inv @ raw_cov @ d_inv.T
    if not (np.all(np.isfinite(cov[idx])) and np.all(cov[idx, 0, 0] > 0)):
        raise OptionError("COTS: the covariance of the variance fit is not finite")
    corrected = alpha - bias
    corrected[~usable] = np.nan
    k = idx.size
    g_bar, h_bar = corrected[idx].mean(axis=0)  # = a_c, to round-off
    var_g = cov[idx, 0, 0].mean() / k
    var_h = cov[idx, 1, 1].mean() / k
    cov_gh = cov[idx, 0, 1].mean() / k
    s0 = h_bar / g_bar
    grad = np.array([-h_bar / g_bar**2, 1.0 / g_bar])  # ∂S0/∂(G, H)
    sig = np.array([[var_g, cov_gh], [cov_gh, var_h]])
    var_s0 = float(grad @ sig @ grad)
    cov_gs0 = float(sig[0] @ grad)
    emp = d_inv @ np.cov(alpha[idx].T) @ d_inv.T / k
    var_s0_emp = float(grad @ emp @ grad)
    roi0 = stack[idx, top : top + h, left : left + w]
    return CotsSpot(
        gain=float(g_bar),
        gain_se=float(np.sqrt(var_g)),
        offset=float(s0),
        offset_se=float(np.sqrt(max(var_s0, 0.0))),
        gain_offset_cov=cov_gs0,
        gain_scatter_se=float(np.sqrt(emp[0, 0])),
        offset_scatter_se=float(np.sqrt(max(var_s0_emp, 0.0))),
        n_frames=int(F),
        n_used=int(k),
        n_saturated=int(saturated.sum()),
        width=float(fit.params[idx, 2].mean()),
        spot_counts=float(fit.params[idx, 3].mean()),
        mean_counts=roi0.mean(axis=0),
        mean_counts_se=roi0.std(axis=0, ddof=1) / np.sqrt(k),
        frame_gain=corrected[:, 0],
        frame_gain_offset=corrected[:, 1],
        frame_bias=bias,
        frame_cov=cov,
        frame_params=fit.params,
        frame_shift=shift,
        usable=usable,
    )


def _frame_hat_moments(expected, jac, idx, read_var):
    """Hat-matrix moments (:func:`_hat_moments`) and leverages of the frames ``idx``, a
    chunk of frames at a time (n × n per frame); NaN for the other frames."""
    F, n = expected.shape
    names = [a + b for a in ("mm", "ff", "mf", "mmf") for b in ("_e", "_1")] + ["read_var", "mmf_s"]
    mom = {k: np.full((F, n), np.nan) for k in names}
    leverage = np.full((F, n), np.nan)
    for lo in range(0, idx.size, _CHUNK):
        ch = idx[lo : lo + _CHUNK]
        qh = _thin_q(jac[ch])
        hat = qh @ np.swapaxes(qh, 1, 2)
        leverage[ch] = np.einsum("fii->fi", hat)
        for k, val in _hat_moments(expected[ch], hat, read_var[ch]).items():
            mom[k][ch] = val
    return mom, leverage


def _corrected_truth(alpha, usable, mom, expected, need, cumulants):
    """The truth a_c = (G, H) that the frames' variance fits estimate.

    Solves ``mean_f α*_f(a_c) = mean_f α̂_f``, with α*_f where frame f's fit lands on
    average (:func:`_pseudo_true`); the per-frame α̂_f scatter by ~30 %: too much to
    evaluate a nonlinear bias at each one. Frames whose fitted signal falls below the
    corrected offset (v ≤ 0 there) are left out of ``usable`` (in place) and the solve
    repeated. Returns a_c, ``d(a_c)/d(mean α̂)`` (which carries the frames' scatter to
    a_c) and α*_f(a_c) of the usable frames.
    """
    for _attempt in range(5):
        idx = np.flatnonzero(usable)
        need(idx, "variance fit")
        sub = {k: val[idx] for k, val in mom.items()}
        e_u = expected[idx]
        warm = {}

        def predicted(point, sub=sub, e_u=e_u, warm=warm):
            out, root, _ = _pseudo_true(
                sub, e_u, np.tile(point, (len(e_u), 1)), cumulants, start=warm.get("root")
            )
            warm["root"] = root  # the root at a nearby point: a warm start
            return out.mean(axis=0)

        def jacobian_of_predicted(point, e_u=e_u):
            jb = np.empty((2, 2))
            for j in range(2):
                hstep = np.zeros(2)
                hstep[j] = 1e-5 * (abs(point[j]) + (abs(point[0]) * np.ptp(e_u) if j else 0))
                jb[:, j] = (predicted(point + hstep) - predicted(point - hstep)) / (2 * hstep[j])
            return jb

        a_raw = alpha[idx].mean(axis=0)
        a_c = a_raw.copy()
        jb = jacobian_of_predicted(a_c)
        for _it in range(50):  # a root (no objective): Newton's chord method
            step = np.linalg.solve(jb, a_raw - predicted(a_c))
            if not np.all(np.isfinite(step)):
                a_c = np.full(2, np.nan)
                break
            a_c = a_c + step
            if np.all(np.abs(step) <= 1e-10 * (np.abs(a_c) + abs(a_c[0]))):
                break
        bad = ~np.all(a_c[0] * e_u - a_c[1] > 0, axis=1)
        if np.all(np.isfinite(a_c)) and a_c[0] > 0 and not bad.any():
            break
        if not bad.any() or bad.all():
            break
        usable[idx[bad]] = False
    if not (np.all(np.isfinite(a_c)) and a_c[0] > 0) or bad.any():
        raise OptionError(
            "COTS: the bias correction of the variance fit did not converge "
            f"(corrected G = {a_c[0]:.4g} ADU/e-); too few pixels with signal?"
        )
    d_inv = np.linalg.inv(jacobian_of_predicted(a_c))
    fit_point = _pseudo_true(
        sub, e_u, np.tile(a_c, (idx.size, 1)), cumulants, start=warm.get("root")
    )[0]
    return a_c, d_inv, fit_point
