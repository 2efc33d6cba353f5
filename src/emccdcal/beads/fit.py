"""Bead fitting: the intensity of every bead in every frame, with the exact noise model.

The paper's validation (Ryan et al. 2021, Methods; docs/beads.md) images fluorescent beads
at every gain set-point and fits each bead in each frame by maximum likelihood: the
pixel model is the pixel-integrated Gaussian spot of :mod:`emccdcal.model.psf`,

    E_k(θ) = N · P_k(x, y, s) + b,        θ = (x, y, s, N, b),

in photoelectrons (e⁻) per pixel per frame, and the likelihood of the raw counts is the
exact camera noise model of every pixel,

    ln L(θ) = Σ_k ln p(S_k | E_k(θ), g_k, φ_k, S0_k, σ_k),

Poisson–normal at 1×, Poisson–gamma–normal at any other set-point, with the pixel's own
offset S0_k and read noise σ_k (ADU, from that set-point's darks) and the calibration
under test (φ_k in e⁻/ADU and g_k, the gain at the set-point). A wrong gain scales every
fitted intensity by the ratio of true to assumed gain, which is what the consistency
metric of :mod:`emccdcal.beads.validation` detects.

How it is computed
------------------
All beads and frames of an acquisition are fitted together, as arrays of shape
(beads × frames, box pixels); nothing loops over frames.

1. **Start** (Gaussian approximation): counts are turned into photoelectrons,
   ``y = (S − S0)·φ/g``, with variance ``F²E + (σφ/g)²`` (F² = 1 at 1×, 2 otherwise).
   Each bead's mean image over the frames is fitted first, then every frame, by
   Levenberg–Marquardt on that Gaussian likelihood.
2. **Exact fit**: the data are fixed, so for every pixel of every frame ln p(S | E) is a
   smooth function of E alone. :class:`emccdcal.model.noise.LogpmfTable` tabulates it exactly
   (the FFT evaluator of :mod:`emccdcal.model.noise`, each pixel's own parameters) at Chebyshev
   nodes in √E over the range of E the start found for that pixel, widened; values and
   the first two derivatives by E then cost a few dozen operations per pixel. The
   interpolation error is below 1e-7 nats (tested against :func:`emccdcal.model.noise.logpmf`).
   Levenberg–Marquardt then maximises the exact likelihood; if a frame ends with a pixel
   outside its tabulated range, the range is widened, that pixel re-tabulated and the
   frame refitted.
3. **Standard errors** from the inverse of the observed Gauss–Newton information
   ``Σ_k (−∂² ln p/∂E²)_k ∇E_k ∇E_kᵀ`` at the optimum (its expectation is the Fisher
   information; the term with the model's second derivatives has expectation zero and is
   left out).

Frames whose fit did not converge, whose spot left the box or whose information matrix
is not positive definite are flagged (``converged`` False); their values are kept.

Coordinates are those of :mod:`emccdcal.model.psf`: pixel (r, c) is centred at integer indices,
``x`` runs along columns and ``y`` along rows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import OptionError
from ..model import noise, psf

__all__ = [
    "DEFAULT_HALF_SIZE",
    "DEFAULT_WIDTH",
    "BeadFits",
    "mean_image",
    "detect_beads",
    "fit_beads",
]

#: Half-width Δ of the fitting box (pixel): boxes are (2Δ + 1) × (2Δ + 1).
DEFAULT_HALF_SIZE = 4
#: Expected spot standard deviation (pixel), used for detection and as a starting value.
DEFAULT_WIDTH = 1.3

_NP = len(psf.PARAMETERS)
#: Frames fitted per batch: bounds the memory of the Jacobians (~1 kB per frame and pixel).
_BATCH_FRAMES = 4096
#: A fit that no step improves any more counts as converged if its Newton decrement (the
#: log-likelihood still to gain, ×2) is below this (nats): far below statistical noise.
_STUCK_DECREMENT = 1e-3


@dataclass(frozen=True)
class BeadFits:
    """Per-frame fits of the beads of one acquisition.

    Attributes
    ----------
    positions : ndarray of int, shape (B, 2)
        (row, col) of every bead's box centre, pixel.
    params : ndarray, shape (B, F, 5)
        Fitted parameters per bead and frame, in the order of
        :data:`emccdcal.model.psf.PARAMETERS`: ``x`` (column) and ``y`` (row) of the centre in
        sensor pixel coordinates, ``width`` (pixel), ``intensity`` N (e⁻ per frame) and
        ``background`` b (e⁻ per pixel per frame).
    se : ndarray, shape (B, F, 5)
        Standard errors of ``params`` (same units); NaN where the information matrix is
        not positive definite.
    loglik : ndarray, shape (B, F)
        Maximised log-likelihood of each bead's box in each frame (nats).
    converged : ndarray of bool, shape (B, F)
        The fit converged inside the box with a usable information matrix.
    iterations : int
        Levenberg–Marquardt iterations of the exact fit (largest over frames).
    retabulated : int
        Pixels whose table range had to be widened after the first exact fit.
    n_saturated : int
        Counts at the ADC maximum, left out of the likelihood.
    """

    positions: np.ndarray
    params: np.ndarray
    se: np.ndarray
    loglik: np.ndarray
    converged: np.ndarray
    iterations: int
    retabulated: int
    n_saturated: int

    @property
    def intensity(self) -> np.ndarray:
        """Fitted intensities N, shape (B, F), e⁻ per frame."""
        return self.params[..., 3]

    @property
    def intensity_se(self) -> np.ndarray:
        """Standard errors of the intensities, shape (B, F), e⁻."""
        return self.se[..., 3]


# --------------------------------------------------------------------------------------
# Detection
# --------------------------------------------------------------------------------------
def mean_image(frames, offset, *, chunk_frames=256) -> np.ndarray:
    """Offset-subtracted mean image of a stack, ADU.

    Parameters
    ----------
    frames : array_like, shape (F, R, C)
        Raw counts (ADU); a memory map is read in chunks of ``chunk_frames``.
    offset : array_like, shape (R, C) or scalar
        Offset S0 (ADU).

    Returns
    -------
    ndarray, shape (R, C)
        Mean over frames of ``frames − offset``, ADU.
    """
    n = frames.shape[0]
    if n == 0:
        raise OptionError("mean_image needs at least one frame")
    total = np.zeros(frames.shape[1:])
    for f0 in range(0, n, chunk_frames):
        total += np.asarray(frames[f0:f0 + chunk_frames]).sum(axis=0, dtype=np.float64)
    return total / n - np.asarray(offset, dtype=float)


def detect_beads(frames, offset, *, width=DEFAULT_WIDTH, half_size=DEFAULT_HALF_SIZE,
                 min_separation=None, snr=8.0) -> psf.BeadSearch:
    """Find isolated beads on the offset-subtracted mean image of a stack.

    Parameters
    ----------
    frames : array_like, shape (F, R, C)
        Raw counts (ADU).
    offset : array_like, shape (R, C)
        Offset map of the same set-point (ADU).
    width, half_size, min_separation, snr
        As :func:`emccdcal.model.psf.find_beads`: expected spot SD (pixel), box half-width Δ
        (pixel), least distance between beads (pixel; default 2Δ + 1) and the detection
        threshold in robust noise SDs.

    Returns
    -------
    emccdcal.model.psf.BeadSearch
        Accepted positions and the candidates rejected at the edge or for crowding.
    """
    return psf.find_beads(mean_image(frames, offset), width=width, half_size=half_size,
                          min_separation=min_separation, snr=snr)


# --------------------------------------------------------------------------------------
# Pixel log-likelihoods as functions of E: (ll, d1, d2) per pixel
# --------------------------------------------------------------------------------------
def _gaussian_terms(E, y, var_read, f2, var_scale=1.0):
    """Gaussian approximation of ln p in photoelectron units, and its E-derivatives.

    ``y`` ~ N(E, v) with ``v = (f2·E⁺ + var_read)·var_scale``. Returns ll, d1 and the
    expected information ``1/v + v'²/(2v²)`` (positive) in place of −d2.
    """
    Ep = np.maximum(E, 0.0)
    v = (f2 * Ep + var_read) * var_scale
    dv = np.where(E > 0, f2 * var_scale, 0.0)
    r = y - E
    ll = -0.5 * r * r / v - 0.5 * np.log(v)
    d1 = r / v + 0.5 * r * r * dv / v**2 - 0.5 * dv / v
    info = 1.0 / v + 0.5 * dv**2 / v**2
    return ll, d1, info


# --------------------------------------------------------------------------------------
# Levenberg–Marquardt over many small problems at once
# --------------------------------------------------------------------------------------
def _lower_upper(half_size):
    h = half_size + 0.5
    lower = np.array([-h, -h, 0.3, 1e-3, 0.0])
    upper = np.array([h, h, 3.0 * half_size, np.inf, np.inf])
    return lower, upper


def _solve(H, g, lam, free=None):
    """Marquardt step ``(H + λ·diag(H) + ε·I)⁻¹ g`` for a batch of 5×5 systems.

    ``free`` (m, 5) bool: parameters held at a bound are left out (their step is 0).
    """
    if free is not None:
        fixed = ~free
        H = np.where(fixed[:, :, None] | fixed[:, None, :], 0.0, H)
        H = H + fixed[:, :, None] * np.eye(_NP)
        g = np.where(free, g, 0.0)
    diag = np.einsum("mii->mi", H)
    ridge = lam[:, None] * diag + 1e-12 * (1.0 + diag.max(axis=1, keepdims=True))
    A = H + ridge[:, :, None] * np.eye(_NP)
    try:
        return np.linalg.solve(A, g[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return np.einsum("mij,mj->mi", np.linalg.pinv(A), g)


def _free(p, grad, lower, upper):
    """Parameters not held at a bound by a gradient pointing out of the feasible box."""
    at_lo = (p <= lower + 1e-12 * (1.0 + np.abs(lower))) & (grad < 0)
    finite = np.isfinite(upper)
    at_hi = finite & (p >= np.where(finite, upper, 0.0) * (1 - 1e-12) - 1e-12) & (grad > 0)
    return ~(at_lo | at_hi)


def _levenberg_marquardt(objective, p0, lower, upper, *, tol, max_iter, active=None):
    """Maximise ``objective`` for every row of ``p0`` (M, 5) at once.

    ``objective(p, sel)`` returns ``ll (m,)``, ``grad (m, 5)`` and a positive
    semi-definite curvature ``H (m, 5, 5)`` for the rows ``sel`` at parameters ``p``.
    A row is done when an accepted step leaves a Newton decrement ``gᵀH⁻¹g`` below
    ``tol`` (nats). Returns the parameters, the log-likelihoods, convergence flags and
    the number of iterations.
    """
    p = p0.copy()
    M = p.shape[0]
    todo = np.ones(M, bool) if active is None else active.copy()
    converged = np.zeros(M, bool)
    ll = np.full(M, -np.inf)
    grad = np.zeros((M, _NP))
    H = np.zeros((M, _NP, _NP))
    lam = np.full(M, 1e-3)
    sel = np.flatnonzero(todo)
    for a in range(0, sel.size, _BATCH_FRAMES):
        s = sel[a:a + _BATCH_FRAMES]
        ll[s], grad[s], H[s] = objective(p[s], s)
    bad = ~np.isfinite(ll)
    todo &= ~bad
    it = 0
    while todo.any() and it < max_iter:
        it += 1
        sel = np.flatnonzero(todo)
        for a in range(0, sel.size, _BATCH_FRAMES):
            s = sel[a:a + _BATCH_FRAMES]
            step = _solve(H[s], grad[s], lam[s], _free(p[s], grad[s], lower, upper))
            trial = np.clip(p[s] + step, lower, upper)
            ll_t, g_t, H_t = objective(trial, s)
            ok = np.isfinite(ll_t) & (ll_t >= ll[s] - 1e-10 * np.abs(ll[s]))
            acc = s[ok]
            p[acc], ll[acc], grad[acc], H[acc] = trial[ok], ll_t[ok], g_t[ok], H_t[ok]
            lam[acc] = np.maximum(lam[acc] / 4.0, 1e-9)
            lam[s[~ok]] *= 8.0
            if acc.size:
                free = _free(p[acc], grad[acc], lower, upper)
                dec = np.einsum("mi,mi->m", np.where(free, grad[acc], 0.0),
                                _solve(H[acc], grad[acc], 0.0 * lam[acc], free))
                done = np.abs(dec) < tol
                converged[acc[done]] = True
                todo[acc[done]] = False
            # No step improves any more: the optimum up to round-off if little is left.
            stuck = s[~ok][lam[s[~ok]] > 1e12]
            if stuck.size:
                free = _free(p[stuck], grad[stuck], lower, upper)
                dec = np.einsum("mi,mi->m", np.where(free, grad[stuck], 0.0),
                                _solve(H[stuck], grad[stuck], 0.0 * lam[stuck], free))
                converged[stuck] = np.abs(dec) < _STUCK_DECREMENT
                todo[stuck] = False
    return p, ll, converged, it


# --------------------------------------------------------------------------------------
# The fit
# --------------------------------------------------------------------------------------
def _box_slices(positions, half_size, shape):
    R, C = shape
    pos = np.asarray(positions, dtype=int).reshape(-1, 2)
    bad = (pos[:, 0] < half_size) | (pos[:, 1] < half_size) | \
        (pos[:, 0] >= R - half_size) | (pos[:, 1] >= C - half_size)
    if bad.any():
        r, c = pos[np.argmax(bad)]
        raise OptionError(
            f"bead at (row {r}, col {c}) is closer than half_size = {half_size} px to the "
            f"edge of the {R}×{C} frame; its box does not fit"
        )
    return pos, [(slice(r - half_size, r + half_size + 1), slice(c - half_size, c + half_size + 1))
                 for r, c in pos]


def _pixel_map(name, value, shape, boxes, pos, *, positive=False, at_least=None):
    """Values of a (R, C) map (or scalar) in every bead's box, shape (B, box pixels)."""
    try:
        arr = np.broadcast_to(np.asarray(value, dtype=float), shape)
    except ValueError:
        raise OptionError(f"{name} has shape {np.shape(value)}; expected the frame shape {shape}") from None
    out = np.stack([arr[rs, cs].ravel() for rs, cs in boxes]) if boxes else np.zeros((0, 1))
    bad = ~np.isfinite(out)
    if positive:
        bad |= out <= 0
    if at_least is not None:
        bad |= out < at_least
    if bad.any():
        r, c = pos[int(np.argmax(bad.any(axis=1)))]
        rule = " > 0" if positive else (f" >= {at_least:g}" if at_least is not None else "")
        raise OptionError(
            f"{name} is not finite{rule} in the box of the bead at (row {r}, col {c})"
        )
    return out


def fit_beads(frames, positions, *, offset, read_noise, e_per_adu, em_gain,
              half_size=DEFAULT_HALF_SIZE, width=DEFAULT_WIDTH, adc_max=None,
              max_iter=60, em_model=None) -> BeadFits:
    """Fit every bead in every frame of one acquisition by maximum likelihood.

    Parameters
    ----------
    frames : array_like, shape (F, R, C)
        Raw counts of the acquisition (ADU, never offset-subtracted); a memory map is fine.
    positions : array_like of int, shape (B, 2)
        (row, col) of each bead's box centre (pixel), e.g. from :func:`detect_beads`.
    offset, read_noise : array_like, shape (R, C) or scalar
        Offset S0 and read noise σ of this set-point (ADU).
    e_per_adu : array_like, shape (R, C) or scalar
        φ of the calibration under test (e⁻/ADU).
    em_gain : array_like, shape (R, C) or scalar
        The calibration's gain at this set-point (dimensionless, ≥ 1); exactly 1 means
        no multiplication (the 1× set-point: Poisson–normal model).
    half_size : int
        Box half-width Δ (pixel); boxes are (2Δ + 1)² pixels.
    width : float
        Starting spot SD (pixel).
    adc_max : int, optional
        ADC maximum (ADU); counts at or above it are left out of the likelihood.
    max_iter : int
        Iterations of each Levenberg–Marquardt stage.
    em_model : emccdcal.model.noise.EMModel, optional
        The EM register model of the exact likelihood (default the gamma model).

    Returns
    -------
    BeadFits

    Raises
    ------
    ValueError
        A box crossing the frame's edge, maps that are not finite and positive in a box,
        a gain below 1, or a stack that is not (frames, rows, cols).
    """
    if np.ndim(frames) != 3:
        raise OptionError(f"frames must be a (frames, rows, cols) stack, got shape {np.shape(frames)}")
    half_size = int(half_size)
    if half_size < 2:
        raise OptionError(f"half_size must be at least 2 px, got {half_size}")
    F, R, C = frames.shape
    pos, boxes = _box_slices(positions, half_size, (R, C))
    B = len(pos)
    n = 2 * half_size + 1
    npix = n * n
    S0 = _pixel_map("offset", offset, (R, C), boxes, pos)
    sigma = _pixel_map("read_noise", read_noise, (R, C), boxes, pos, positive=True)
    phi = _pixel_map("e_per_adu", e_per_adu, (R, C), boxes, pos, positive=True)
    g = _pixel_map("em_gain", em_gain, (R, C), boxes, pos, at_least=1.0)
    if B == 0 or F == 0:
        empty = np.zeros((B, F, _NP))
        return BeadFits(pos, empty, empty.copy(), np.zeros((B, F)), np.zeros((B, F), bool),
                        0, 0, 0)
    counts = np.stack([np.asarray(frames[:, rs, cs]).reshape(F, npix) for rs, cs in boxes])
    counts = counts.astype(np.int64)  # (B, F, npix)
    if counts.min() < 0:
        raise OptionError("frames hold negative counts; raw ADU are non-negative")
    weight = np.ones(counts.shape)
    n_sat = 0
    if adc_max is not None:
        sat = counts >= adc_max
        n_sat = int(sat.sum())
        weight[sat] = 0.0

    pn = g == 1.0
    theta = np.where(pn, 1.0 / phi, g / phi)          # ADU per photoelectron (B, npix)
    f2 = np.where(pn, 1.0, 2.0)
    var_read = (sigma / theta) ** 2                     # e⁻², (B, npix)
    y = (counts - S0[:, None, :]) / theta[:, None, :]   # e⁻, (B, F, npix)
    local = np.arange(-half_size, half_size + 1, dtype=float)
    lower, upper = _lower_upper(half_size)

    def model(p):
        img, jac = psf.spot_image(p, local, local, jacobian=True)
        return img.reshape(len(p), npix), jac.reshape(len(p), npix, _NP)

    def curvature(w, J):
        return np.einsum("mk,mki,mkj->mij", w, J, J)

    # ---- 0: each bead's mean image (Gaussian approximation) ---------------------------
    ybar = y.mean(axis=1)  # (B, npix)
    border = np.ones((n, n), bool)
    border[1:-1, 1:-1] = False
    b0 = np.median(ybar[:, border.ravel()], axis=1)
    excess = np.clip(ybar - b0[:, None], 0.0, None)
    N0 = np.maximum(excess.sum(axis=1), 1.0)
    yy, xx = np.meshgrid(local, local, indexing="ij")
    cx = np.clip((excess * xx.ravel()).sum(axis=1) / N0, -1.0, 1.0)
    cy = np.clip((excess * yy.ravel()).sum(axis=1) / N0, -1.0, 1.0)
    p_bead = np.stack([cx, cy, np.full(B, float(width)), N0, np.maximum(b0, 0.0)], axis=1)

    def objective_mean(p, s):
        E, J = model(p)
        ll, d1, info = _gaussian_terms(E, ybar[s], var_read[s], f2[s], 1.0 / F)
        return ll.sum(axis=1), np.einsum("mk,mki->mi", d1, J), curvature(info, J)

    p_bead, _, _, _ = _levenberg_marquardt(objective_mean, p_bead, lower, upper,
                                           tol=1e-6, max_iter=max_iter)

    # ---- 1: every frame, Gaussian approximation --------------------------------------
    M = B * F
    bead_of = np.repeat(np.arange(B), F)
    y_m = y.reshape(M, npix)
    w_m = weight.reshape(M, npix)
    bfr = np.median(y[:, :, border.ravel()], axis=2).reshape(M)
    p1 = np.repeat(p_bead, F, axis=0)
    p1[:, 4] = np.maximum(bfr, 0.0)
    p1[:, 3] = np.maximum((y_m - p1[:, 4:5]).sum(axis=1), 0.1 * p1[:, 3])

    def objective_gauss(p, s):
        E, J = model(p)
        b = bead_of[s]
        ll, d1, info = _gaussian_terms(E, y_m[s], var_read[b], f2[b])
        w = w_m[s]
        return (w * ll).sum(axis=1), np.einsum("mk,mki->mi", w * d1, J), curvature(w * info, J)

    p1, _, conv1, _ = _levenberg_marquardt(objective_gauss, p1, lower, upper, tol=1e-4,
                                           max_iter=max_iter)
    # Frames the approximation could not fit start the exact fit from their bead's median.
    med = np.stack([np.median(p1[bead_of == b][conv1[bead_of == b]], axis=0)
                    if conv1[bead_of == b].any() else p_bead[b] for b in range(B)])
    p1[~conv1] = med[bead_of[~conv1]]

    # ---- 2: exact likelihood through per-pixel tables of ln p(S | E) -------------------
    E1, _ = model(p1)
    E1 = E1.reshape(B, F, npix)
    use = conv1.reshape(B, F)[:, :, None] & np.ones((1, 1, npix), bool)
    lo = np.where(use, E1, np.inf).min(axis=1)
    hi = np.where(use, E1, -np.inf).max(axis=1)
    none = ~np.isfinite(lo)
    lo[none], hi[none] = E1.min(axis=1)[none], E1.max(axis=1)[none]
    lo, hi = _pad_range(lo, hi)
    table = noise.LogpmfTable(
        counts.reshape(-1), np.repeat(np.arange(B), F * npix) * npix
        + np.tile(np.arange(npix), M),
        lo.ravel(), hi.ravel(), g.ravel(), phi.ravel(), S0.ravel(), sigma.ravel(),
        em_model=em_model or noise.EMModel(),
    )
    qbase = np.arange(npix)

    def exact_terms(p, s):
        E, J = model(p)
        idx = (s[:, None] * npix + qbase).ravel()
        lp, d1, d2, out = table.evaluate(E.ravel(), idx)
        shape = E.shape
        return E, J, lp.reshape(shape), d1.reshape(shape), d2.reshape(shape), out.reshape(shape)

    def objective_exact(p, s):
        _, J, lp, d1, d2, _ = exact_terms(p, s)
        w = w_m[s]
        return ((w * lp).sum(axis=1), np.einsum("mk,mki->mi", w * d1, J),
                curvature(w * np.maximum(-d2, 0.0), J))

    p2, ll2, conv2, iters = _levenberg_marquardt(objective_exact, p1, lower, upper,
                                                 tol=1e-7, max_iter=max_iter)
    retab = 0
    for _ in range(4):
        outside = np.zeros(M, bool)
        E_all = np.empty((M, npix))
        out_px = np.zeros((M, npix), bool)
        for a in range(0, M, _BATCH_FRAMES):
            s = np.arange(a, min(M, a + _BATCH_FRAMES))
            E, _, _, _, _, out = exact_terms(p2[s], s)
            E_all[s], out_px[s] = E, out & (w_m[s] > 0)
        outside = out_px.any(axis=1)
        if not outside.any():
            break
        # Widen the ranges of the pixels concerned to cover what the fits need.
        pix = (bead_of[:, None] * npix + qbase)[out_px]
        e_lo, e_hi = table.e_range
        need_lo = np.full(e_lo.size, np.inf)
        need_hi = np.full(e_lo.size, -np.inf)
        np.minimum.at(need_lo, pix, E_all[out_px])
        np.maximum.at(need_hi, pix, E_all[out_px])
        px = np.unique(pix)
        new_lo, new_hi = _pad_range(np.minimum(e_lo[px], need_lo[px]),
                                    np.maximum(e_hi[px], need_hi[px]))
        table.set_range(px, new_lo, new_hi)
        retab += px.size
        p2, ll_r, conv_r, it_r = _levenberg_marquardt(objective_exact, p2, lower, upper,
                                                      tol=1e-7, max_iter=max_iter, active=outside)
        conv2 = np.where(outside, conv_r, conv2)
        ll2 = np.where(outside, ll_r, ll2)
        iters = max(iters, it_r)
    else:
        outside = np.zeros(M, bool)
        for a in range(0, M, _BATCH_FRAMES):
            s = np.arange(a, min(M, a + _BATCH_FRAMES))
            outside[s] = (exact_terms(p2[s], s)[5] & (w_m[s] > 0)).any(axis=1)

    # ---- standard errors: observed Gauss–Newton information ---------------------------
    # A parameter held at its bound (the background at 0) is fixed there: the others'
    # errors are conditional on it, and its own is undefined (NaN).
    se = np.full((M, _NP), np.nan)
    pd = np.zeros(M, bool)
    for a in range(0, M, _BATCH_FRAMES):
        s = np.arange(a, min(M, a + _BATCH_FRAMES))
        _, J, _, d1, d2, _ = exact_terms(p2[s], s)
        free = _free(p2[s], np.einsum("mk,mki->mi", w_m[s] * d1, J), lower, upper)
        info = curvature(w_m[s] * -d2, J)
        info = np.where(free[:, :, None] & free[:, None, :], info, 0.0) \
            + (~free)[:, :, None] * np.eye(_NP)
        # A frame whose fit ran off (non-finite curvature) has no SE, not a crash.
        eig_ok = np.all(np.isfinite(info), axis=(1, 2))
        eig_ok[eig_ok] = np.all(np.linalg.eigvalsh(info[eig_ok]) > 0, axis=1)
        cov = np.full_like(info, np.nan)
        if eig_ok.any():
            cov[eig_ok] = np.linalg.inv(info[eig_ok])
        var = np.where(free, np.einsum("mii->mi", cov), np.nan)
        se[s] = np.sqrt(np.where(var > 0, var, np.nan))
        pd[s] = eig_ok
    inside = np.all((p2 > lower + 1e-9) | (np.arange(_NP) >= 3), axis=1) & \
        np.all((p2 < upper - 1e-9) | (np.arange(_NP) >= 3), axis=1)
    converged = conv2 & pd & inside & ~outside & np.isfinite(ll2)
    params = p2.copy()
    params[:, 0] += np.repeat(pos[:, 1], F)
    params[:, 1] += np.repeat(pos[:, 0], F)
    return BeadFits(
        positions=pos,
        params=params.reshape(B, F, _NP),
        se=se.reshape(B, F, _NP),
        loglik=ll2.reshape(B, F),
        converged=converged.reshape(B, F),
        iterations=int(iters),
        retabulated=int(retab),
        n_saturated=n_sat,
    )


def _pad_range(lo, hi):
    """Table range around [lo, hi] (e⁻): half the span and 5 % more on each side."""
    lo = np.maximum(np.asarray(lo, float), 0.0)
    hi = np.maximum(np.asarray(hi, float), lo)
    span = hi - lo
    new_lo = np.maximum(lo - 0.5 * span - 0.05 * hi, 0.2 * lo)
    new_hi = hi + 0.5 * span + 0.05 * hi + 0.5
    return new_lo, new_hi
