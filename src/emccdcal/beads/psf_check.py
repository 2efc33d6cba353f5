"""How well the spot model fits the beads: the widths the acquisitions share
(:func:`shared_widths`), the oversampled residual image of the fits
(:func:`residual_image`) and the mismatch of a spot model scored on other frames
(:func:`psf_mismatch`)."""

from __future__ import annotations

import math

import numpy as np

from ..errors import OptionError
from ..model import psf

from .fit_errors import _residual_frames


def shared_widths(fits, *, with_se: bool = False):
    """Each bead's spot width over several acquisitions of it (the set-points of a bead
    series): the inverse-variance weighted mean of the widths each acquisition's fit
    found, pixel, shape (B,); with ``with_se`` also its standard error (pixel).

    The PSF is the optics', the same at every set-point; fitted per acquisition, its
    error moves that acquisition's intensities together (a wider spot, a brighter bead),
    which compares set-points through their width errors. One width for all set-points
    takes that error out of the comparison and, at 1×, where the signal-to-noise ratio is
    lowest, replaces a noisy width by one the multiplied set-points measure well. Its
    own error still moves every set-point's intensity against the truth: pass its SE to
    :func:`fit_beads` (``fixed_width_se``) to count it.
    """
    w = np.stack([f.params[:, 0, 2] for f in fits])  # (A, B)
    se = np.stack([f.se[:, 0, 2] for f in fits])
    ok = np.stack([f.converged.any(axis=1) for f in fits]) & np.isfinite(se) & (se > 0)
    weight = np.where(ok, 1.0 / np.where(ok, se, 1.0) ** 2, 0.0)
    total = weight.sum(axis=0)
    width = np.where(
        total > 0,
        (weight * np.where(ok, w, 0.0)).sum(axis=0) / np.where(total > 0, total, 1.0),
        np.nan,
    )
    if not with_se:
        return width
    return width, np.where(total > 0, 1.0 / np.sqrt(np.where(total > 0, total, 1.0)), np.nan)


def _mean_intensity(fit, b):
    """Bead ``b``'s mean intensity over the frames of its residual (e⁻), or NaN."""
    use = _residual_frames(fit.converged[b], fit.intensity[b])
    return float(fit.intensity[b, use].mean()) if use.any() else math.nan


def residual_image(fits, *, oversample=4, per_bead=True, half=None) -> psf.ResidualImage:
    """The oversampled residual image of a bead series: what the Gaussian spot misses,
    per unit intensity, from the fits of several acquisitions of the same beads.

    The paper's second pass (Ryan et al. 2021, Methods): the fitted spots are subtracted
    from the data and the differences kept on a grid finer than the pixels, to be added
    to the PSF model (:class:`emccdcal.model.psf.ResidualImage`, ``fit_beads(...,
    residual=)``). Each bead's mean residual (:attr:`BeadFits.residual`) divided by its
    mean intensity is placed at its pixels' offsets from the bead's fitted centre; the
    beads' different sub-pixel centres (and the stage's moves between set-points) fill
    the fine grid. Values are averaged with inverse-variance weights, spread to the four
    nearest nodes (bilinear weights) and smoothed by normalized convolution with a
    Gaussian of SD ¼ pixel, which also fills the gaps between samples. The image is
    linear in the residuals, so its sampling variance follows exactly from theirs
    (:attr:`ResidualImage.variance`).

    Parameters
    ----------
    fits : sequence of BeadFits
        Fits of the same beads (same ``positions``), e.g. at every set-point, with the
        Gaussian spot alone.
    oversample : int
        Grid nodes per pixel (4).
    per_bead : bool
        One image per bead (default: the PSF changes over the field of view, and a bead's
        own residual is taken at its own centre), or one pooled over all beads.
    half : {None, 0, 1}
        Build the image from the residuals of all frames (None) or of one half of them
        (:attr:`BeadFits.residual_halves`), so that the other half can score it
        (:func:`psf_mismatch`).

    Returns
    -------
    emccdcal.model.psf.ResidualImage
    """
    q = int(oversample)
    if q < 1:
        raise OptionError(f"oversample must be at least 1, got {oversample}")
    if half not in (None, 0, 1):
        raise OptionError(f"half must be None, 0 or 1, got {half!r}")
    fits = list(fits)
    B, n = fits[0].residual.shape[:2]
    h = n // 2
    c = int(np.ceil((h + 1.5) * q))  # nodes from the centre to the edge
    G = 2 * c + 1
    K = B if per_bead else 1
    samples = [[] for _ in range(K)]  # (node row, node col, weight, value)
    for fit in fits:
        if fit.residual.shape[:2] != (B, n) or not np.array_equal(fit.positions, fits[0].positions):
            raise OptionError("residual_image needs fits of the same beads and box size")
        resid, resid_se = _residual_of(fit, half)
        for b in range(B):
            N = _mean_intensity(fit, b)
            if not N > 0:
                continue
            r, se = resid[b] / N, resid_se[b] / N
            good = np.isfinite(r) & np.isfinite(se) & (se > 0)
            dy, dx = _box_offsets(fit, b, n)
            samples[b if per_bead else 0].append(
                (dy[good] * q + c, dx[good] * q + c, 1.0 / se[good] ** 2, r[good])
            )
    values, variance = np.zeros((2, K, G, G))
    for k, parts in enumerate(samples):
        if not parts:
            continue
        gy, gx, w, r = (np.concatenate(p) for p in zip(*parts))
        a, bb = _spread(gy, G, q / 4.0), _spread(gx, G, q / 4.0)  # (samples, G) each
        num = a.T @ ((w * r)[:, None] * bb)
        den = a.T @ (w[:, None] * bb)
        var_num = (a**2).T @ (w[:, None] * bb**2)  # Var(w r) = w, for w = 1/SE²
        keep = den > 1e-3 * den.max()
        safe = np.where(keep, den, 1.0)
        values[k] = np.where(keep, num / safe, 0.0)
        variance[k] = np.where(keep, var_num / safe**2, 0.0)
    return psf.ResidualImage(values, q, variance)


def _spread(g, size, sd):
    """Each sample's weights on a line of ``size`` nodes: bilinear to its two nearest
    nodes, then a Gaussian of SD ``sd`` nodes (truncated at 4 SD and normalised, as
    :func:`scipy.ndimage.gaussian_filter`), shape (samples, size). The image's smoothing
    is separable, so a sample's weight at node (i, j) is the product of its two lines'."""
    radius = int(4.0 * sd + 0.5)
    kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sd) ** 2)
    kernel /= kernel.sum()
    low = np.floor(g).astype(int)
    frac = g - low
    out = np.zeros((len(g), size))
    nodes = np.arange(size)
    for shift, weight in ((0, 1.0 - frac), (1, frac)):
        d = nodes[None, :] - (low + shift)[:, None]
        inside = np.abs(d) <= radius
        out += weight[:, None] * np.where(inside, kernel[np.clip(d + radius, 0, 2 * radius)], 0.0)
    return out


def _box_offsets(fit, b, n):
    """Offsets (dy, dx) of bead ``b``'s n × n box pixels from its fitted centre (its
    shared position), pixel, shape (n, n) each: where its residual image is read."""
    x0, y0 = fit.params[b, np.argmax(fit.converged[b]), :2]
    local = np.arange(n) - n // 2
    return (
        (fit.positions[b, 0] + local - y0)[:, None] * np.ones(n),
        np.ones(n)[:, None] * (fit.positions[b, 1] + local - x0),
    )


def _residual_of(fit, half):
    """The mean residual and its SE of all frames (``half`` None) or of one half."""
    if half is None:
        return fit.residual, fit.residual_se
    return fit.residual_halves[half], fit.residual_halves_se[half]


def psf_mismatch(fit, *, half=None, image=None) -> dict:
    """How far the spot model is from the data of one acquisition, pooled over its beads.

    Parameters
    ----------
    fit : BeadFits
    half : {None, 0, 1}
        Score the mean residual of all frames (None) or of one half of them
        (:attr:`BeadFits.residual_halves`): the half a residual image was *not* built on
        gives a goodness of fit on data the image has not seen.
    image : emccdcal.model.psf.ResidualImage, optional
        The residual image in the fitted model, built on other frames: its own sampling
        variance (:meth:`~emccdcal.model.psf.ResidualImage.variance_at`, times N²) is
        added to each pixel's, since the image's noise is a difference the held-out
        frames see. Without it χ² reads about 1 + 1/(frames pooled into the image).

    Returns
    -------
    dict
        ``chi2_per_pixel``: mean over beads of Σ_k (residual_k / SE_k)² / pixels, ≈ 1 when
        the spot model describes the mean image to within its noise; ``chi2_per_pixel_se``:
        its sampling SD under a right model, √(2/pixels)/beads summed in quadrature;
        ``missed_fraction``: mean over beads of Σ_k residual_k / N, the fraction of the
        bead's intensity the model misses inside its box (signed); ``abs_fraction``: the
        same of |residual_k|.
    """
    resid, resid_se = _residual_of(fit, half)
    n = resid.shape[1]
    chi2, pixels, missed, absolute = [], [], [], []
    for b in range(len(fit.positions)):
        N = _mean_intensity(fit, b)
        r, var = resid[b], resid_se[b] ** 2
        if image is not None and N > 0:
            dy, dx = _box_offsets(fit, b, n)
            var = var + N**2 * image.variance_at(np.full(n, b if len(image) > 1 else 0), dy, dx)
        good = np.isfinite(r) & np.isfinite(var) & (var > 0)
        if not N > 0 or not good.any():
            continue
        chi2.append(float(np.sum(r[good] ** 2 / var[good]) / good.sum()))
        pixels.append(int(good.sum()))
        missed.append(float(r[good].sum() / N))
        absolute.append(float(np.abs(r[good]).sum() / N))
    mean = lambda v: float(np.mean(v)) if v else float("nan")
    return {
        "chi2_per_pixel": mean(chi2),
        "chi2_per_pixel_se": (
            float(np.sqrt(np.sum(2.0 / np.array(pixels))) / len(pixels)) if pixels else float("nan")
        ),
        "missed_fraction": mean(missed),
        "abs_fraction": mean(absolute),
    }
