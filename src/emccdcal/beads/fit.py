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

What is shared
--------------
A bead's position (x, y) and spot width s are the same in all its frames (the stage is
stable within an acquisition; the PSF is the optics'), and so, by default, is its
background b; its intensity N changes from frame to frame. The fit maximises the bead's
summed likelihood over the shared parameters and every frame's N. The paper fitted all
five in every frame on its own; at low signal that biases the intensities (free width
and intensity trade off, and the maximum-likelihood width of a faint spot is biased):
3000 e⁻ beads at 1× came out +3 % high, and 1000 e⁻ beads converged in 69 % of frames and
came out +27 % high. Sharing the shape makes every frame's fit linear in N and removes
both. A background per frame (``background="frame"``) is held at its bound b = 0 in the
frames where noise would take it below, which biases it up and N down (−0.5 % at 1× with
10 e⁻/px); a shared one is not clipped, and the mean of N over frames stays unbiased even
where the real background fluctuates from frame to frame (docs/beads.md).
``fixed_width`` holds each bead's width at a given value: ``emccdcal validate`` pools the
widths of all set-points (:func:`shared_widths`) and fits again with them, so that a
width error does not differ from set-point to set-point.

A PSF that is not Gaussian
--------------------------
Each fit keeps every bead's mean residual (data − model over its frames,
:attr:`BeadFits.residual`). :func:`residual_image` places them, per unit intensity, on a
grid finer than the pixels at each pixel's offset from the bead's centre; ``fit_beads(...,
residual=)`` adds that image to the Gaussian spot, ``E = N·(P + R) + b``: the paper's
second pass. :func:`psf_mismatch` says how well a fit's model describes the mean images;
every fit also keeps the mean residual of each half of its frames
(:func:`frame_halves`), so that an image built on one half is scored on the other, its
own sampling variance (:attr:`~emccdcal.model.psf.ResidualImage.variance`) counted.

How it is computed
------------------
All beads and frames of an acquisition are fitted together, as arrays of shape
(beads × frames, box pixels); nothing loops over frames.

1. **Start** (Gaussian approximation): counts are turned into photoelectrons,
   ``y = (S − S0)·φ/g``, with variance ``F²E + (σφ/g)²`` (F² = 1 at 1×, 2 otherwise).
   Each bead's mean image over the frames is fitted first (Levenberg–Marquardt), which
   gives its shape; every frame's N (and b) starts from least squares on that shape;
   then the joint fit below runs on this Gaussian likelihood.
2. **Exact fit**: the data are fixed, so for every pixel of every frame ln p(S | E) is a
   smooth function of E alone. :class:`emccdcal.model.pointwise.LogpmfTable` tabulates it exactly
   (the FFT evaluator of :mod:`emccdcal.model.noise`, each pixel's own parameters) at Chebyshev
   nodes in √E over the range of E the start found for that pixel, widened; values and
   the first two derivatives by E then cost a few dozen operations per pixel. The
   interpolation error is below 1e-7 nats (tested against :func:`emccdcal.model.noise.logpmf`).
   The joint fit then maximises the exact likelihood: Newton steps on each whole bead,
   its Hessian an arrow (shared parameters against every frame's own block) solved by
   eliminating the frames' blocks (the Schur complement), with the damping of the
   package's one optimizer (:func:`emccdcal._optimize.maximize`). If a frame ends with a pixel outside its tabulated range, the range
   is widened, that pixel re-tabulated and the bead refitted.
3. **Standard errors** from the Gauss–Newton information
   ``Σ_k (−∂² ln p/∂E²)_k ∇E_k ∇E_kᵀ`` at the optimum (its expectation is the Fisher
   information): a frame's own parameters conditional on the shared ones (what scatters
   from frame to frame), and the shared ones' from the Schur complement (the same in all
   the bead's frames).

A bead whose fit did not converge, or whose spot left the box, has all its frames flagged
(``converged`` False), as has a frame whose information is not positive; values are kept.

Coordinates are those of :mod:`emccdcal.model.psf`: pixel (r, c) is centred at integer indices,
``x`` runs along columns and ``y`` along rows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import defaults
from .._optimize import ArrowLayout, schur
from .._util import weighted_gram
from ..errors import OptionError
from ..model import noise, pointwise, psf
from .psf_check import psf_mismatch, residual_image, shared_widths  # the public names
from .fit_rows import _BATCH_FRAMES, _lower_upper, _evaluate_rows, _fit_rows, _joint_fit
from .fit_errors import (
    _NP,
    RESIDUAL_SPLITS,
    _joint_errors,
    _mean_residual,
    _offset_error,
    _shared_error_of_mean,
    _width_effect,
    frame_halves,
)

__all__ = [
    "DEFAULT_HALF_SIZE",
    "DEFAULT_WIDTH",
    "BeadFits",
    "mean_image",
    "detect_beads",
    "fit_beads",
    "shared_widths",
    "residual_image",
    "psf_mismatch",
    "frame_halves",
    "RESIDUAL_SPLITS",
]

#: Half-width Δ of the fitting box (pixel): boxes are (2Δ + 1) × (2Δ + 1).
DEFAULT_HALF_SIZE = defaults.BEAD_HALF_SIZE
#: Expected spot standard deviation (pixel), used for detection and as a starting value.
DEFAULT_WIDTH = psf.DEFAULT_WIDTH


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
    iterations : ndarray of int, shape (B, 3)
        Each bead's optimizer iterations in the three stages: its mean image, the joint
        fit of the Gaussian approximation, the exact joint fit (refits included).
    retabulated : int
        Pixels whose table range had to be widened after the first exact fit.
    n_saturated : int
        Counts at the ADC maximum, left out of the likelihood.
    residual : ndarray, shape (B, 2Δ + 1, 2Δ + 1)
        Each bead's box: data minus fitted model, mean over its converged frames (e⁻ per
        pixel per frame; NaN for a bead without any). What the spot model misses: the
        input of :func:`residual_image`.
    residual_se : ndarray, shape (B, 2Δ + 1, 2Δ + 1)
        Standard error of ``residual``, e⁻: the SD over frames / √frames and the offset
        map's own error (``offset_se``, the same in every frame) in quadrature.
    residual_halves, residual_halves_se : ndarray, shape (2, B, 2Δ + 1, 2Δ + 1)
        The same over each half of the frames (:func:`frame_halves`): a residual image
        built on one half is scored on the other (:func:`psf_mismatch`).
    residual_split : str
        How the frames were halved: ``"alternate"`` or ``"time"``.
    intensity_offset_se : ndarray, shape (B,)
        Standard error of each bead's mean intensity over its frames from the offset
        map's own error (``offset_se``), e⁻; 0 where the map is taken as exact. It is the
        same in every frame, so it does not average away over frames, and is not in
        ``se``.
    intensity_shared_se : ndarray, shape (B,)
        Standard error of each bead's mean intensity over its converged frames from the
        error of its shared parameters (position, width, background: one estimate for
        all its frames), e⁻. ``se`` of a frame's intensity is conditional on them (what
        scatters from frame to frame); this part is common to the frames, so it does not
        average away either. NaN for a bead without converged frames.
    """

    positions: np.ndarray
    params: np.ndarray
    se: np.ndarray
    loglik: np.ndarray
    converged: np.ndarray
    iterations: np.ndarray
    retabulated: int
    n_saturated: int
    residual: np.ndarray
    residual_se: np.ndarray
    intensity_offset_se: np.ndarray
    intensity_shared_se: np.ndarray = None
    residual_halves: np.ndarray = None
    residual_halves_se: np.ndarray = None
    residual_split: str = "alternate"

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
        total += np.asarray(frames[f0 : f0 + chunk_frames]).sum(axis=0, dtype=np.float64)
    return total / n - np.asarray(offset, dtype=float)


def detect_beads(
    frames,
    offset,
    *,
    width=DEFAULT_WIDTH,
    half_size=DEFAULT_HALF_SIZE,
    min_separation=None,
    snr=8.0,
) -> psf.BeadSearch:
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
    return psf.find_beads(
        mean_image(frames, offset),
        width=width,
        half_size=half_size,
        min_separation=min_separation,
        snr=snr,
    )


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
# The fit
# --------------------------------------------------------------------------------------
def _box_slices(positions, half_size, shape):
    R, C = shape
    pos = np.asarray(positions, dtype=int).reshape(-1, 2)
    bad = (
        (pos[:, 0] < half_size)
        | (pos[:, 1] < half_size)
        | (pos[:, 0] >= R - half_size)
        | (pos[:, 1] >= C - half_size)
    )
    if bad.any():
        r, c = pos[np.argmax(bad)]
        raise OptionError(
            f"bead at (row {r}, col {c}) is closer than half_size = {half_size} px to the "
            f"edge of the {R}×{C} frame; its box does not fit"
        )
    return pos, [
        (slice(r - half_size, r + half_size + 1), slice(c - half_size, c + half_size + 1))
        for r, c in pos
    ]


def _pixel_map(name, value, shape, boxes, pos, *, positive=False, at_least=None):
    """Values of a (R, C) map (or scalar) in every bead's box, shape (B, box pixels)."""
    try:
        arr = np.broadcast_to(np.asarray(value, dtype=float), shape)
    except ValueError:
        raise OptionError(
            f"{name} has shape {np.shape(value)}; expected the frame shape {shape}"
        ) from None
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


def fit_beads(
    frames,
    positions,
    *,
    offset,
    read_noise,
    e_per_adu,
    em_gain,
    half_size=DEFAULT_HALF_SIZE,
    width=DEFAULT_WIDTH,
    adc_max=None,
    max_iter=60,
    em_model=None,
    fixed_width=None,
    fixed_width_se=None,
    background="shared",
    residual=None,
    offset_se=None,
    residual_split="alternate",
) -> BeadFits:
    """Fit every bead in every frame of one acquisition by maximum likelihood: the bead's
    position, width and background shared by its frames, each frame's intensity.

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
        The EM register model of the exact likelihood (default
        :data:`emccdcal.defaults.DEFAULT_EM_MODEL`, as everywhere).
    fixed_width : float or array_like (B,), optional
        Each bead's spot SD (pixel), held fixed (e.g. measured at all set-points at once);
        by default it is fitted, shared by the bead's frames.
    fixed_width_se : float or array_like (B,), optional
        The standard error of ``fixed_width`` (pixel): its effect on each bead's mean
        intensity enters ``intensity_shared_se``. By default the width is taken as exact.
    background : {"shared", "frame"}
        One background per bead for all its frames (default), or one per frame. A
        per-frame background is held at its bound 0 in the frames where noise would take
        it below, which biases it up and the intensity down (−0.5 % at 1× with 10 e⁻/px
        of background; docs/beads.md); one shared by the frames is not clipped, and the
        mean intensity over frames stays unbiased even if the background fluctuates.
    residual : emccdcal.model.psf.ResidualImage, optional
        Added to the Gaussian spot (the paper's second pass): ``E = N·(P + R) + b`` with R
        at each pixel's offset from the fitted centre; one image for all beads or one per
        bead, in the order of ``positions`` (:func:`residual_image`).
    offset_se : array_like, shape (R, C) or scalar, optional
        Standard error of the offset map (ADU), e.g. read noise / √(dark frames); gives
        ``intensity_offset_se``. By default the map is taken as exact.
    residual_split : {"alternate", "time"}
        How the frames are halved for ``residual_halves`` (:func:`frame_halves`).

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
        raise OptionError(
            f"frames must be a (frames, rows, cols) stack, got shape {np.shape(frames)}"
        )
    half_size = int(half_size)
    if half_size < 2:
        raise OptionError(f"half_size must be at least 2 px, got {half_size}")
    F, R, C = frames.shape
    pos, boxes = _box_slices(positions, half_size, (R, C))
    B = len(pos)
    lower, upper = _lower_upper(half_size)
    if background not in ("shared", "frame"):
        raise OptionError(f"background must be 'shared' or 'frame', got {background!r}")
    frame_halves(0, residual_split)  # checks the name
    if residual is not None and len(residual) not in (1, B):
        raise OptionError(
            f"the residual image has {len(residual)} images; expected 1 or one per bead ({B})"
        )
    if fixed_width is not None:
        fixed = np.broadcast_to(np.asarray(fixed_width, dtype=float), (B,)).copy()
        if not np.all((fixed > lower[2]) & (fixed < upper[2])):
            raise OptionError(
                f"fixed_width must be between {lower[2]:g} and {upper[2]:g} px "
                f"for a box of half-size {half_size}; got {fixed.tolist()}"
            )
    n = 2 * half_size + 1
    S0 = _pixel_map("offset", offset, (R, C), boxes, pos)
    sigma = _pixel_map("read_noise", read_noise, (R, C), boxes, pos, positive=True)
    phi = _pixel_map("e_per_adu", e_per_adu, (R, C), boxes, pos, positive=True)
    g = _pixel_map("em_gain", em_gain, (R, C), boxes, pos, at_least=1.0)
    s0_se = _pixel_map(
        "offset_se", 0.0 if offset_se is None else offset_se, (R, C), boxes, pos, at_least=0.0
    )
    if B == 0 or F == 0:
        return _no_fits(pos, F, n, residual_split)
    counts, weight, n_sat = _box_counts(frames, boxes, adc_max)

    box = _Boxes(counts, weight, S0, sigma, phi, g, half_size, residual)
    # 0: each bead's mean image (Gaussian approximation): its shape
    p_bead, it_mean = _fit_rows(
        box.objective_mean, box.start(width), lower, upper, tol=5e-7, max_iter=max_iter
    )
    # 1: every frame, Gaussian approximation, the bead's shape shared. Position, width (and
    # background) are the bead's own, the same in every frame; the intensity changes from
    # frame to frame (the module's notes say why).
    if fixed_width is not None:
        p_bead[:, 2] = fixed
    shared, frame = _shared_and_frame(fixed_width is not None, background)
    layout = ArrowLayout(F, _NP, shared, frame, lower, upper)
    p1, _, it_gauss = _joint_fit(
        box.objective_gauss,
        box.frame_start(p_bead, background),
        layout,
        tol=5e-5,
        max_iter=max_iter,
    )
    # 2: the exact likelihood through per-pixel tables of ln p(S | E)
    box.tabulate(p1, em_model or noise.EMModel())
    p2, conv_b, it_exact, E_all, info_all, outside, retab = _fit_exact(box, p1, layout, max_iter)
    # the standard errors from the joint information, and what the model misses
    ll2, grad, H = _evaluate_rows(box.objective_exact, p2, np.arange(B * F))
    pb, Hb = p2.reshape(B, F, _NP), H.reshape(B, F, _NP, _NP)
    arrow = schur(Hb, shared, frame)  # S, H_ff⁻¹, H_sf: the errors and responses below
    se, sensitivity, shared_cov = _joint_errors(arrow, shared, frame)
    frame_ok = np.all(np.isfinite(Hb), axis=(2, 3)) & (Hb[..., 3, 3] > 0)
    inside = np.all((pb[..., :3] > lower[:3] + 1e-9) & (pb[..., :3] < upper[:3] - 1e-9), axis=2)
    converged = (
        conv_b[:, None]
        & frame_ok
        & inside
        & ~outside.reshape(B, F)
        & np.isfinite(ll2.reshape(B, F))
    )
    width_var = np.zeros(B)  # the held width's own error, where given
    if fixed_width is not None and fixed_width_se is not None:
        width_se = np.broadcast_to(np.asarray(fixed_width_se, dtype=float), (B,))
        width_var = (_width_effect(Hb, arrow, shared_cov, shared, frame, converged) * width_se) ** 2
    r_mean, r_var, half_mean, half_var, W = _mean_residual(
        box, p2, E_all, info_all, converged, residual_split, (s0_se / box.theta) ** 2
    )
    n_offset_se = _offset_error(box, pb, converged, sorted(shared + frame), W, s0_se)
    params = p2.copy()
    params[:, 0] += np.repeat(pos[:, 1], F)
    params[:, 1] += np.repeat(pos[:, 0], F)
    return BeadFits(
        positions=pos,
        params=params.reshape(B, F, _NP),
        se=se,
        loglik=ll2.reshape(B, F),
        converged=converged,
        iterations=np.stack([it_mean, it_gauss, it_exact], axis=1),
        retabulated=int(retab),
        n_saturated=n_sat,
        residual=r_mean.reshape(B, n, n),
        residual_se=np.sqrt(r_var).reshape(B, n, n),
        residual_halves=half_mean.reshape(2, B, n, n),
        residual_halves_se=np.sqrt(half_var).reshape(2, B, n, n),
        residual_split=residual_split,
        intensity_offset_se=np.where(converged.any(axis=1), n_offset_se, np.nan),
        intensity_shared_se=_shared_error_of_mean(sensitivity, shared_cov, converged, width_var),
    )


def _no_fits(pos, F, n, residual_split) -> BeadFits:
    """The fits of no bead or no frame: empty arrays of the right shapes."""
    B = len(pos)
    empty = np.zeros((B, F, _NP))
    none = np.full((B, n, n), np.nan)
    return BeadFits(
        pos,
        empty,
        empty.copy(),
        np.zeros((B, F)),
        np.zeros((B, F), bool),
        np.zeros((B, 3), int),
        0,
        0,
        none,
        none.copy(),
        np.full(B, np.nan),
        np.full(B, np.nan),
        np.stack([none, none]),
        np.stack([none, none]),
        residual_split,
    )


def _box_counts(frames, boxes, adc_max):
    """Every bead's box in every frame, ``(B, F, npix)`` int64, with the pixels' weights
    (0 where saturated at ``adc_max``) and the number of saturated pixels."""
    F = frames.shape[0]
    counts = np.stack([np.asarray(frames[:, rs, cs]).reshape(F, -1) for rs, cs in boxes])
    counts = counts.astype(np.int64)
    if counts.min() < 0:
        raise OptionError("frames hold negative counts; raw ADU are non-negative")
    weight = np.ones(counts.shape)
    n_sat = 0
    if adc_max is not None:
        sat = counts >= adc_max
        n_sat = int(sat.sum())
        weight[sat] = 0.0
    return counts, weight, n_sat


def _shared_and_frame(width_fixed: bool, background: str):
    """The parameters a bead shares over its frames and those each frame has its own
    (indices into x, y, width, intensity, background)."""
    shared = [0, 1] if width_fixed else [0, 1, 2]
    frame = [3, 4] if background == "frame" else [3]
    if background == "shared":
        shared = shared + [4]
    return shared, frame


class _Boxes:
    """The data of every bead's box in every frame, in photoelectrons, and the spot model
    and log-likelihoods the fit stages maximise.

    Counts become ``y = (S − S0)/θ`` (e⁻), θ the ADU per photoelectron (1/φ at 1×, g/φ
    otherwise), with read-out variance ``(σ/θ)²`` and excess-noise factor F² (1 at 1×, 2
    otherwise) for the Gaussian approximation. Rows are (bead, frame) pairs, bead-major.
    """

    def __init__(self, counts, weight, S0, sigma, phi, g, half_size, residual):
        B, F, npix = counts.shape
        self.B, self.F, self.npix, self.M = B, F, npix, B * F
        self.counts, self.S0, self.sigma, self.phi, self.g = counts, S0, sigma, phi, g
        pn = g == 1.0
        self.theta = np.where(pn, 1.0 / phi, g / phi)  # ADU per e⁻, (B, npix)
        self.f2 = np.where(pn, 1.0, 2.0)
        self.var_read = (sigma / self.theta) ** 2  # e⁻², (B, npix)
        self.y = (counts - S0[:, None, :]) / self.theta[:, None, :]  # e⁻, (B, F, npix)
        self.weight = weight
        self.y_m, self.w_m = self.y.reshape(self.M, npix), weight.reshape(self.M, npix)
        self.ybar = self.y.mean(axis=1)  # (B, npix)
        self.bead_of = np.repeat(np.arange(B), F)
        self.local = np.arange(-half_size, half_size + 1, dtype=float)
        yy, xx = np.meshgrid(self.local, self.local, indexing="ij")
        self.yy, self.xx = yy.ravel(), xx.ravel()
        self.residual = residual
        self.image_of = np.zeros(B, int) if residual is None or len(residual) == 1 else np.arange(B)
        self.table = None

    def model(self, p, beads):
        """Expected e⁻ and its Jacobian for rows ``p`` (box coordinates) of ``beads``."""
        img, jac = psf.spot_image(p, self.local, self.local, jacobian=True)
        E, J = img.reshape(len(p), self.npix), jac.reshape(len(p), self.npix, _NP)
        if self.residual is not None:
            Rv, R_dy, R_dx = self.residual.evaluate(
                self.image_of[beads], self.yy - p[:, 1:2], self.xx - p[:, 0:1]
            )
            N = p[:, 3:4]
            E = E + N * Rv
            J[..., 3] += Rv
            J[..., 0] -= N * R_dx  # the offsets move against the centre
            J[..., 1] -= N * R_dy
        return E, J

    @staticmethod
    def _curvature(w, J):
        return weighted_gram(w, J)

    def start(self, width):
        """Each bead's (x, y, s, N, b) from the moments of its mean image."""
        n = self.local.size
        border = np.ones((n, n), bool)
        border[1:-1, 1:-1] = False
        b0 = np.median(self.ybar[:, border.ravel()], axis=1)
        excess = np.clip(self.ybar - b0[:, None], 0.0, None)
        N0 = np.maximum(excess.sum(axis=1), 1.0)
        cx = np.clip((excess * self.xx).sum(axis=1) / N0, -1.0, 1.0)
        cy = np.clip((excess * self.yy).sum(axis=1) / N0, -1.0, 1.0)
        return np.stack([cx, cy, np.full(self.B, float(width)), N0, np.maximum(b0, 0.0)], axis=1)

    def frame_start(self, p_bead, background):
        """Every frame's row: the bead's shape, with the intensity and background from
        least squares on that shape (a shared background the mean over frames)."""
        B, F = self.B, self.F
        p1 = np.repeat(p_bead, F, axis=0)
        unit, _ = self.model(
            np.concatenate([p_bead[:, :3], np.ones((B, 1)), np.zeros((B, 1))], axis=1), np.arange(B)
        )
        for b in range(B):
            X = np.stack([unit[b], np.ones(self.npix)], axis=1)
            coef = np.linalg.lstsq(X, self.y[b].T, rcond=None)[0]  # (2, F)
            p1[self.bead_of == b, 3] = np.maximum(coef[0], 0.1 * p_bead[b, 3])
            p1[self.bead_of == b, 4] = np.maximum(coef[1], 0.0)
        if background == "shared":  # shared columns start equal in all the bead's frames
            p1[:, 4] = np.repeat(p1[:, 4].reshape(B, F).mean(axis=1), F)
        return p1

    def objective_mean(self, p, s):
        """Each bead's mean image under the Gaussian approximation (rows: beads)."""
        E, J = self.model(p, s)
        ll, d1, info = _gaussian_terms(E, self.ybar[s], self.var_read[s], self.f2[s], 1.0 / self.F)
        return ll.sum(axis=1), np.einsum("mk,mki->mi", d1, J), self._curvature(info, J)

    def objective_gauss(self, p, s):
        """Every frame under the Gaussian approximation (rows: bead-frames)."""
        b = self.bead_of[s]
        E, J = self.model(p, b)
        ll, d1, info = _gaussian_terms(E, self.y_m[s], self.var_read[b], self.f2[b])
        w = self.w_m[s]
        return (
            (w * ll).sum(axis=1),
            np.einsum("mk,mki->mi", w * d1, J),
            self._curvature(w * info, J),
        )

    def tabulate(self, p, em_model):
        """Tables of the exact ln p(S | E) of every pixel over the range of E that the
        rows ``p`` need, widened."""
        B, F, npix = self.B, self.F, self.npix
        E1 = self.model(p, self.bead_of)[0].reshape(B, F, npix)
        lo, hi = _pad_range(E1.min(axis=1), E1.max(axis=1))
        self.table = pointwise.LogpmfTable(
            self.counts.reshape(-1),
            np.repeat(np.arange(B), F * npix) * npix + np.tile(np.arange(npix), self.M),
            lo.ravel(),
            hi.ravel(),
            self.g.ravel(),
            self.phi.ravel(),
            self.S0.ravel(),
            self.sigma.ravel(),
            em_model=em_model,
        )

    def exact_terms(self, p, s):
        """E, J, ln p and its first two E-derivatives, and the pixels outside their
        table's range, for rows ``s``."""
        E, J = self.model(p, self.bead_of[s])
        idx = (s[:, None] * self.npix + np.arange(self.npix)).ravel()
        lp, d1, d2, out = self.table.evaluate(E.ravel(), idx)
        shape = E.shape
        return E, J, lp.reshape(shape), d1.reshape(shape), d2.reshape(shape), out.reshape(shape)

    def objective_exact(self, p, s):
        """Every frame under the exact likelihood (rows: bead-frames)."""
        _, J, lp, d1, d2, _ = self.exact_terms(p, s)
        w = self.w_m[s]
        return (
            (w * lp).sum(axis=1),
            np.einsum("mk,mki->mi", w * d1, J),
            self._curvature(w * np.maximum(-d2, 0.0), J),
        )

    def all_terms(self, p):
        """Every row's E, its information −∂² ln p/∂E² and the weighted pixels outside
        their table's range, shape (M, npix) each."""
        M, npix = self.M, self.npix
        E_all, info_all = np.empty((M, npix)), np.empty((M, npix))
        out_px = np.zeros((M, npix), bool)
        for a in range(0, M, _BATCH_FRAMES):
            s = np.arange(a, min(M, a + _BATCH_FRAMES))
            E, _, _, _, d2, out = self.exact_terms(p[s], s)
            E_all[s], info_all[s] = E, np.maximum(-d2, 0.0)
            out_px[s] = out & (self.w_m[s] > 0)
        return E_all, info_all, out_px


def _fit_exact(box, p, layout, max_iter, rounds=5):
    """The exact joint fit; where a frame ends with a pixel outside its table's range, the
    range is widened, that pixel re-tabulated and the bead refitted (at most
    ``rounds − 1`` refits). Returns the parameters, per-bead convergence and iterations,
    every row's E and information at the end, the rows with a pixel still outside, and
    the pixels re-tabulated."""
    B, F, npix = box.B, box.F, box.npix
    p, converged, iterations = _joint_fit(
        box.objective_exact, p, layout, tol=5e-8, max_iter=max_iter
    )
    retab = 0
    for round_ in range(rounds):  # the last round only evaluates
        E_all, info_all, out_px = box.all_terms(p)
        outside = out_px.any(axis=1)
        if not outside.any() or round_ == rounds - 1:
            break
        # Widen the ranges of the pixels concerned to cover what the fits need.
        pix = (box.bead_of[:, None] * npix + np.arange(npix))[out_px]
        e_lo, e_hi = box.table.e_range
        need_lo = np.full(e_lo.size, np.inf)
        need_hi = np.full(e_lo.size, -np.inf)
        np.minimum.at(need_lo, pix, E_all[out_px])
        np.maximum.at(need_hi, pix, E_all[out_px])
        px = np.unique(pix)
        new_lo, new_hi = _pad_range(
            np.minimum(e_lo[px], need_lo[px]), np.maximum(e_hi[px], need_hi[px])
        )
        box.table.set_range(px, new_lo, new_hi)
        retab += px.size
        redo = outside.reshape(B, F).any(axis=1)
        p, conv_r, it_r = _joint_fit(
            box.objective_exact, p, layout, tol=5e-8, max_iter=max_iter, beads=redo
        )
        converged = np.where(redo, conv_r, converged)
        iterations = iterations + it_r
    return p, converged, iterations, E_all, info_all, outside, retab


def _pad_range(lo, hi):
    """Table range around [lo, hi] (e⁻): half the span and 5 % more on each side."""
    lo = np.maximum(np.asarray(lo, float), 0.0)
    hi = np.maximum(np.asarray(hi, float), lo)
    span = hi - lo
    new_lo = np.maximum(lo - 0.5 * span - 0.05 * hi, 0.2 * lo)
    new_hi = hi + 0.5 * span + 0.05 * hi + 0.5
    return new_lo, new_hi
