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
#: (c3, c4) of the gamma register (:func:`register_cumulants`), COTS as published.
GAMMA_CUMULANTS = (3.0, 12.0)


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


def _inv2(a):
    """Inverse of a stack of 2×2 matrices, shape (..., 2, 2)."""
    det = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
    inv = np.empty_like(a)
    inv[..., 0, 0] = a[..., 1, 1]
    inv[..., 1, 1] = a[..., 0, 0]
    inv[..., 0, 1] = -a[..., 0, 1]
    inv[..., 1, 0] = -a[..., 1, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        return inv / det[..., None, None]


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
# 3. Bias and covariance of the per-frame (G, H)
# --------------------------------------------------------------------------------------
#: Frames whose (n × n) hat matrices are held at once.
_CHUNK = 128


def _thin_q(jacobian):
    """Orthonormal basis (F, n, p) of the columns of J: the hat matrix is Q Qᵀ."""
    j = np.asarray(jacobian, float)
    return np.linalg.qr(j.reshape(j.shape[0], -1, j.shape[-1]))[0]


def _hat_moments(expected, hat, read_var):
    """The parts of the noise moments that depend on the hat matrix only, per frame.

    With M = I − f, the moments of the residuals r = M ε and of the fitted values' error
    δ = f ε are linear in the pixel variances v, and v = 2 (G E − H) is linear in (G, H):
    ``X @ v = 2 G (X @ E) − 2 H (X @ 1)`` for X = M∘M, f∘f, M∘f, M∘M∘f. Those eight
    (F, n) arrays, the read-noise variance σ² (ADU², ``read_var``) and ``(M∘M∘f) @ σ²``
    (the third cumulant is the register's alone: read noise has none) are all the bias
    needs, at any (G, H).
    """
    e = np.asarray(expected, float)
    n = e.shape[1]
    m_mat = np.eye(n)[None] - hat
    out = {"read_var": np.broadcast_to(read_var, e.shape).astype(float)}
    for name, x in (("mm", m_mat**2), ("ff", hat**2), ("mf", m_mat * hat), ("mmf", m_mat**2 * hat)):
        out[name + "_e"] = np.einsum("fij,fj->fi", x, e)
        out[name + "_1"] = x.sum(axis=2)
    out["mmf_s"] = np.einsum("fij,fj->fi", m_mat**2 * hat, out["read_var"])
    return out


def _noise_moments(mom, e, alpha, cumulants):
    """Per pixel: v, E r², E δ², E r δ, E r² δ, E r² δ² at true (G, H) = alpha."""
    g, hh = alpha[:, :1], alpha[:, 1:]

    def lin(name):
        return 2 * g * mom[name + "_e"] - 2 * hh * mom[name + "_1"]

    v = 2.0 * (g * e - hh)
    m, d, c = lin("mm"), lin("ff"), lin("mf")
    t = cumulants[0] * g * (lin("mmf") - mom["mmf_s"])  # κ3 = c3 G (v − σ²)
    return v, m, d, t, m * d + 2.0 * c**2


def _uu(w, e):
    """Σ_i w_i u_i u_iᵀ per frame for u_i = ∂v_i/∂(G, H) = (2 E_i, −2): shape (F, 2, 2)."""
    out = np.empty((len(e), 2, 2))
    out[:, 0, 0] = 4 * np.sum(w * e * e, axis=1)
    out[:, 0, 1] = out[:, 1, 0] = -4 * np.sum(w * e, axis=1)
    out[:, 1, 1] = 4 * np.sum(w, axis=1)
    return out


def _quad(c, e):
    """u_iᵀ C u_i per pixel for a per-frame 2×2 C, shape (F, n)."""
    return 4 * (c[:, :1, 0] * e * e - 2 * c[:, :1, 1] * e + c[:, 1:, 1])


def _expected_score(ast, e, moments):
    """E ψ(α*) of the variance fit at (G*, H*) = ast, and its Jacobian by α*.

    ψ = ∂L/∂(G, H) with the fitted E_i; expanded to second order in δ = f ε.
    """
    _, m, d, t, erd = moments
    gs = ast[:, :1]
    iv = 1.0 / (2.0 * (gs * e - ast[:, 1:]))
    iv2 = iv * iv
    iv3 = iv2 * iv
    iv4 = iv2 * iv2
    s_u = iv - m * iv2 + 4 * gs * t * iv3 + 4 * gs**2 * (d * iv3 - 3 * erd * iv4)
    s_e1 = -2 * t * iv2 + 4 * gs * (-d * iv2 + 2 * erd * iv3)
    score = np.stack(
        [2 * np.sum(s_u * e, axis=1) + s_e1.sum(axis=1), -2 * np.sum(s_u, axis=1)], axis=1
    )
    # derivatives by v* (which moves with α* as ∂v*/∂α* = (2E, −2)) and by G* itself
    du_dv = 2 * m * iv3 - iv2 - 12 * gs * t * iv4 + 4 * gs**2 * (-3 * d * iv4 + 12 * erd * iv4 * iv)
    du_dg = 4 * t * iv3 + 8 * gs * (d * iv3 - 3 * erd * iv4)
    de_dv = 4 * t * iv3 + 4 * gs * (2 * d * iv3 - 6 * erd * iv4)
    de_dg = 4 * (-d * iv2 + 2 * erd * iv3)
    ddv = du_dv * 2 * e + du_dg  # ∂s_u/∂G*
    jac = np.empty((len(e), 2, 2))
    jac[:, 0, 0] = np.sum(2 * e * ddv + de_dv * 2 * e + de_dg, axis=1)
    jac[:, 0, 1] = -2 * np.sum(2 * e * du_dv + de_dv, axis=1)
    jac[:, 1, 0] = -2 * np.sum(ddv, axis=1)
    jac[:, 1, 1] = 4 * np.sum(du_dv, axis=1)
    return score, jac


def _fourth_cumulant(g, v, read_var, cumulants):
    """κ4 = c4 G² (v − σ²) per pixel: the register's; read noise (Gaussian) has none."""
    return cumulants[1] * g**2 * np.maximum(v - read_var, 0.0)


def _small_sample_bias(e, alpha, read_var, cumulants):
    """O(1/n) bias of the variance fit with E_i known (second-order M-estimator expansion).

    Zero for Gaussian noise; not zero for the register's heavy-tailed noise (κ4).
    """
    g = alpha[:, :1]
    v = 2.0 * (g * e - alpha[:, 1:])
    iv2 = 1.0 / v**2
    wv = 2 * v**2 + _fourth_cumulant(g, v, read_var, cumulants)  # Var ε_i²
    a_inv = _inv2(_uu(iv2, e))
    c0 = a_inv @ _uu(wv * iv2 * iv2, e) @ a_inv
    coef = (2 * _quad(c0, e) - 2 * wv * iv2 * _quad(a_inv, e)) * iv2 / v
    inner = np.stack([2 * np.sum(coef * e, axis=1), -2 * np.sum(coef, axis=1)], axis=1)
    return np.einsum("fjk,fk->fj", a_inv, inner)


def _pseudo_true(mom, e, alpha, cumulants, start=None, max_iter=50):
    """Where each frame's variance fit lands on average when the truth is ``alpha``.

    Solves E ψ_f(α*) = 0 (Newton from ``start``, default ``alpha``, kept inside v* > 0)
    and adds the small-sample bias. Returns that (F, 2), the root α* itself (a warm start
    for a nearby ``alpha``) and whether every frame's solve converged.
    """
    moments = _noise_moments(mom, e, alpha, cumulants)
    ast = (alpha if start is None else start).copy()
    ok = np.zeros(len(e), bool)
    for _ in range(max_iter):
        score, jac = _expected_score(ast, e, moments)
        step = -np.einsum("fij,fj->fi", _inv2(jac), score)
        step[~np.isfinite(step)] = 0.0
        t = np.ones(len(e))
        for _half in range(30):
            trial = ast + t[:, None] * step
            bad = ~np.all(trial[:, :1] * e - trial[:, 1:] > 0, axis=1) | (trial[:, 0] <= 0)
            if not bad.any():
                break
            t[bad] *= 0.5
        ast = trial
        ok = np.all(np.abs(t[:, None] * step) <= 1e-10 * (np.abs(ast) + np.abs(ast[:, :1])), axis=1)
        if ok.all():
            break
    return ast + _small_sample_bias(e, alpha, mom["read_var"], cumulants), ast, ok


def _covariance(expected, qh, alpha, alpha_fit, read_var, cumulants):
    """Sandwich covariance of the per-frame (Ĝ, Ĥ), not bias-corrected.

    ``alpha`` sets the true noise (v, κ4), ``alpha_fit`` is where the fit lands on
    average (:func:`_pseudo_true`), where the objective's curvature is taken.
    ``qh`` (F, n, p) is an orthonormal basis of the Jacobian's columns (f = qh qhᵀ).
    O(n² p) per frame.
    """
    e = np.asarray(expected, float)
    g = alpha[:, :1]
    v = 2.0 * (g * e - alpha[:, 1:])
    vs = 2.0 * (alpha_fit[:, :1] * e - alpha_fit[:, 1:])
    k4 = _fourth_cumulant(g, v, read_var, cumulants)
    qt = np.swapaxes(qh, 1, 2)
    hat = qh @ qt
    m2 = (np.eye(e.shape[1])[None] - hat) ** 2
    m = np.einsum("fij,fj->fi", m2, v)
    # M V M = V − f V − V f + f V f, with f = Q Qᵀ of rank p.
    vq = v[:, :, None] * qh
    fv = qh @ np.swapaxes(vq, 1, 2)
    mvm = -fv - np.swapaxes(fv, 1, 2) + qh @ (qt @ vq) @ qt
    idx = np.arange(e.shape[1])
    mvm[:, idx, idx] += v
    u = np.stack([2.0 * e, np.full_like(e, -2.0)], axis=-1)
    cu = u / vs[..., None] ** 2
    # Cov(r_i², r_j²) = 2 (MVM)_ij² + Σ_k M_ik² κ4_k M_jk²
    b = 2 * np.swapaxes(cu, 1, 2) @ (mvm**2 @ cu)
    w = np.swapaxes(m2, 1, 2) @ cu  # (F, n, 2): Σ_i M_ik² c_i
    b += np.einsum("fk,fkj,fkl->fjl", k4, w, w)
    a = np.einsum("fi,fij,fik->fjk", (2 * m / vs - 1) / vs**2, u, u)
    a_inv = _inv2(a)
    return a_inv @ b @ a_inv


def register_cumulants(register, gain, e_per_adu):
    """The register's third and fourth pixel cumulants per unit of register variance.

    For compound-Poisson input through a register whose one-electron output X has raw
    moments μ_k, a pixel's register variance is ``v_reg = λ μ_2/φ²`` (ADU²) and its higher
    cumulants ``κ_k = λ μ_k/φ^k``. In COTS's gain G (F² = 2: ``G = g F²/(2φ)``) they are
    ``κ3 = c3·G·v_reg`` and ``κ4 = c4·G²·v_reg`` with ``c3 = 2 g μ3/μ2²`` and
    ``c4 = 4 g² μ4/μ2³``: 3 and 12 for the gamma register (an exponential X), 2.98 and
    11.84 at 5× for a 536-stage cascade.

    Parameters
    ----------
    register : a register of :mod:`emccdcal.model.noise` (``EMModel(...).register``)
    gain : float
        COTS's G under F² = 2, ADU/e⁻ (where the gain g is read: the cumulants vary slowly).
    e_per_adu : float
        φ, e⁻/ADU.

    Returns
    -------
    (float, float)
        c3 and c4 (dimensionless).

    Examples
    --------
    >>> from emccdcal.model.noise import EMModel
    >>> register_cumulants(EMModel("gamma").register, 1.3, 3.859)
    (3.0, 12.0)
    >>> c3, c4 = register_cumulants(EMModel("cascade", 536).register, 1.163, 3.859)
    >>> round(c3, 3), round(c4, 2)
    (2.982, 11.84)
    """
    g = float(register.gain_from_gain_f2(2.0 * gain * e_per_adu)[0])
    mu = register.single_electron_moments(max(g, 1.0))
    return (float(2.0 * g * mu[2] / mu[1] ** 2), float(4.0 * g**2 * mu[3] / mu[1] ** 3))


def variance_bias_covariance(
    expected, jacobian, alpha, *, read_noise=0.0, cumulants=GAMMA_CUMULANTS
):
    """Bias and sandwich covariance of the per-frame variance fit (G, H).

    The fitted E_i come from the same counts as the residuals, so the residuals are
    smaller than the noise (``E r_i² = v_i − 2 f_ii v_i + (fVf)_ii``, f the hat matrix)
    and the plain variance fit is biased low: by O(p/n) (p = 5 spot parameters, n pixels)
    on average, much more where a few bright pixels carry high leverage. The bias here is
    where the fit lands on average, α* − α: the root of the expected score with the
    residual and fitted-value moments to second order in f ε (a first-order theory in
    1/n, solved rather than linearised, since the shift is ~10 %), plus the O(1/n)
    small-sample bias of the variance fit itself (zero for Gaussian noise, not for the
    register's skewed, heavy-tailed noise). The third and fourth cumulants are the
    register's alone, ``κ3 = c3 G (v − σ²)`` and ``κ4 = c4 G² (v − σ²)``
    (:func:`register_cumulants`; c3 = 3, c4 = 12 for the gamma register): the Gaussian
    read noise σ adds to the variance only. The covariance is the sandwich at α*.
    Derivation: ``docs/cots.md``.

    Parameters
    ----------
    expected : array_like, shape (F, n) or (F, h, w)
        Fitted expected counts E_i (ADU).
    jacobian : array_like, shape (F, n, 5) or (F, h, w, 5)
        ∂E_i/∂(spot parameters) at the fits (:attr:`SpotFit.jacobian`).
    alpha : array_like, shape (F, 2) or (2,)
        True (G, H) = (G, G·S0) (ADU/e⁻, ADU²/e⁻): where the bias is evaluated.
    read_noise : float or array_like of shape (F, n) or (F, h, w)
        Read-noise SD σ of the pixels (ADU); 0 as in COTS as published.
    cumulants : (float, float)
        (c3, c4) of :func:`register_cumulants`; the gamma register's by default.

    Returns
    -------
    bias : ndarray, shape (F, 2)
        E[α̂] − α: subtract it from α̂ (evaluated at the truth, or at the corrected value).
    cov : ndarray, shape (F, 2, 2)
        Covariance of the uncorrected α̂.
    """
    e = np.asarray(expected, float).reshape(len(expected), -1)
    alpha = np.broadcast_to(np.asarray(alpha, float), (len(e), 2)).copy()
    read_var = np.square(np.asarray(read_noise, float))
    read_var = np.broadcast_to(read_var.reshape(len(e), -1) if read_var.ndim else read_var, e.shape)
    qh = _thin_q(jacobian)
    mom = _hat_moments(e, qh @ np.swapaxes(qh, 1, 2), read_var)
    fit_point = _pseudo_true(mom, e, alpha, cumulants)[0]
    return fit_point - alpha, _covariance(e, qh, alpha, fit_point, read_var, cumulants)


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
