"""The bead image model: a pixel-integrated Gaussian spot on a flat background, and bead finding.

Coordinates are in pixels. Pixel ``(r, c)`` covers ``[r - 1/2, r + 1/2] × [c - 1/2, c + 1/2]``,
so a spot centred on a pixel has its centre at that pixel's integer indices. ``y`` runs along
rows, ``x`` along columns.

The spot model (Mortensen & Flyvbjerg 2016, step 1; Mortensen et al. 2010; docs/beads.md) is

    E_k = N · P_x(k) · P_y(k) + b,
    P_x(k) = ½ [erf((x_k + ½ − x0) / (√2 s)) − erf((x_k − ½ − x0) / (√2 s))],

the expected signal of pixel k (photoelectrons, or any unit that N and b share), with the
spot's centre (x0, y0) in pixels, its standard deviation s in pixels, its total N and the
background b per pixel. The parameter vector is always ordered as :data:`PARAMETERS`.

A PSF that is not Gaussian is described by adding an oversampled residual image
(:class:`ResidualImage`, the paper's second pass): ``E_k = N·(P_k + R(y_k − y0, x_k − x0)) + b``,
R the part of a unit spot's pixel values the Gaussian misses, as a function of the pixel
centre's offset from the spot's centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage, special

from .. import defaults
from ..errors import OptionError

__all__ = [
    "DEFAULT_WIDTH",
    "PARAMETERS",
    "pixel_fractions",
    "spot_image",
    "ResidualImage",
    "BeadSearch",
    "find_beads",
]

#: Order of the spot parameters: centre column x0 and row y0 (pixel), width s (pixel),
#: total signal N and background b per pixel (photoelectrons).
#: Expected spot standard deviation (pixel) of a bead, for detection and as a fit's
#: starting value: one default for ``validate`` and ``cots`` (``--width``).
DEFAULT_WIDTH = defaults.PSF_WIDTH
PARAMETERS = ("x", "y", "width", "intensity", "background")

_SQRT2 = np.sqrt(2.0)


def _edges(centre, coords, width):
    """Standardised pixel edges (coords ∓ ½ − centre)/width, shape (..., n)."""
    centre = np.asarray(centre, float)[..., None]
    width = np.asarray(width, float)[..., None]
    coords = np.asarray(coords, float)
    return (coords + 0.5 - centre) / width, (coords - 0.5 - centre) / width


def pixel_fractions(centre, coords, width, *, derivatives=False):
    """Fraction of a 1-D Gaussian's mass in each pixel, and its derivatives.

    Parameters
    ----------
    centre : array_like, shape (...)
        Centre of the Gaussian (pixel).
    coords : array_like, shape (n,)
        Pixel-centre coordinates (pixel).
    width : array_like, shape (...)
        Standard deviation (pixel), > 0.
    derivatives : bool
        Also return the derivatives by the centre and by the width.

    Returns
    -------
    P : ndarray, shape (..., n)
        The fractions (dimensionless).
    dP_dcentre, dP_dwidth : ndarray, shape (..., n)
        Only with ``derivatives`` (per pixel).
    """
    upper, lower = _edges(centre, coords, width)
    frac = 0.5 * (special.erf(upper / _SQRT2) - special.erf(lower / _SQRT2))
    if not derivatives:
        return frac
    pdf_u = np.exp(-0.5 * upper**2) / np.sqrt(2 * np.pi)
    pdf_l = np.exp(-0.5 * lower**2) / np.sqrt(2 * np.pi)
    w = np.asarray(width, float)[..., None]
    d_centre = -(pdf_u - pdf_l) / w
    d_width = -(upper * pdf_u - lower * pdf_l) / w
    return frac, d_centre, d_width


def spot_image(params, rows, cols, *, jacobian=False):
    """Expected image of spots on a flat background.

    Parameters
    ----------
    params : array_like, shape (..., 5)
        Spot parameters in the order of :data:`PARAMETERS`: x0, y0, s (pixel), N, b.
    rows, cols : array_like, shape (h,) and (w,)
        Row and column coordinates of the image's pixels (pixel), in the frame of x0, y0.
    jacobian : bool
        Also return the derivatives of every pixel's expectation by every parameter.

    Returns
    -------
    E : ndarray, shape (..., h, w)
        Expected signal per pixel, in the units of N and b.
    J : ndarray, shape (..., h, w, 5)
        Only with ``jacobian``: ∂E/∂params.
    """
    params = np.asarray(params, float)
    x0, y0, s, n, b = np.moveaxis(params, -1, 0)
    if not jacobian:
        px = pixel_fractions(x0, cols, s)
        py = pixel_fractions(y0, rows, s)
        return n[..., None, None] * py[..., :, None] * px[..., None, :] + b[..., None, None]
    px, dpx_dx, dpx_ds = pixel_fractions(x0, cols, s, derivatives=True)
    py, dpy_dy, dpy_ds = pixel_fractions(y0, rows, s, derivatives=True)
    shape = py[..., :, None] * px[..., None, :]
    nn = n[..., None, None]
    image = nn * shape + b[..., None, None]
    jac = np.stack(
        [
            nn * py[..., :, None] * dpx_dx[..., None, :],
            nn * dpy_dy[..., :, None] * px[..., None, :],
            nn
            * (dpy_ds[..., :, None] * px[..., None, :] + py[..., :, None] * dpx_ds[..., None, :]),
            shape,
            np.ones_like(shape),
        ],
        axis=-1,
    )
    return image, jac


class ResidualImage:
    """What the pixel-integrated Gaussian misses of a spot, per unit intensity, as a smooth
    function of a pixel centre's offset from the spot's centre.

    The paper's second pass (Ryan et al. 2021, Methods): the fits' residuals, stored on a
    grid finer than the pixels and added to the spot model. Values are pixel-integrated
    already (each is what a whole pixel at that offset receives, as a fraction of the
    spot's intensity N), so evaluating at a pixel's offset needs no further binning; a
    bicubic spline interpolates between the grid's nodes and gives the derivatives by the
    centre.

    Parameters
    ----------
    values : array_like, shape (K, G, G)
        One image per spot (K beads) or one for all (K = 1): the fraction of N, at offsets
        ``(i − (G − 1)/2) / oversample`` pixels (i = 0 … G − 1) along rows then columns.
    oversample : int
        Grid nodes per pixel.
    variance : array_like, shape (K, G, G), optional
        The sampling variance of ``values`` (fraction²), where they were estimated from
        data (:func:`emccdcal.beads.psf_check.residual_image`): what a goodness of fit on other
        data must allow for (:meth:`variance_at`). Default 0: the image taken as exact.

    Examples
    --------
    >>> r = ResidualImage(np.zeros((1, 9, 9)), oversample=2)
    >>> r.extent
    2.0
    >>> [float(v.sum()) for v in r.evaluate(np.zeros(1, int), np.zeros((1, 3)), np.zeros((1, 3)))]
    [0.0, 0.0, 0.0]
    """

    def __init__(self, values, oversample, variance=None):
        from scipy.interpolate import RectBivariateSpline

        self.values = np.asarray(values, float)
        if (
            self.values.ndim != 3
            or self.values.shape[1] != self.values.shape[2]
            or self.values.shape[1] < 4
        ):
            raise OptionError(
                f"a residual image is (K, G, G) with G >= 4, got shape {self.values.shape}"
            )
        self.variance = (
            np.zeros_like(self.values) if variance is None else np.asarray(variance, float)
        )
        if self.variance.shape != self.values.shape or np.any(self.variance < 0):
            raise OptionError(
                f"a residual image's variance is non-negative and of the "
                f"values' shape {self.values.shape}, got {self.variance.shape}"
            )
        self.oversample = int(oversample)
        G = self.values.shape[1]
        self.extent = (G - 1) / 2 / self.oversample  # pixel
        nodes = np.linspace(-self.extent, self.extent, G)
        self._splines = [RectBivariateSpline(nodes, nodes, v, kx=3, ky=3, s=0) for v in self.values]

    def __len__(self):
        return len(self.values)

    def evaluate(self, which, dy, dx):
        """The residual at offsets ``(dy, dx)`` (pixel) and its derivatives by them.

        Parameters
        ----------
        which : array_like of int, shape (m,)
            The image of each row (0 when there is one for all).
        dy, dx : ndarray, shape (m, n)
            Offsets of pixel centres from the spot's centre, along rows and columns
            (pixel). Beyond the grid the residual is 0.

        Returns
        -------
        R, dR_ddy, dR_ddx : ndarray, shape (m, n)
            Fraction of the spot's intensity, and its derivatives (per pixel).
        """
        which = np.asarray(which, int)
        out = [np.zeros(dy.shape) for _ in range(3)]
        inside = (np.abs(dy) <= self.extent) & (np.abs(dx) <= self.extent)
        for k in np.unique(which):
            rows = which == k
            sel = inside[rows]
            yy, xx = dy[rows][sel], dx[rows][sel]
            spline = self._splines[k if len(self._splines) > 1 else 0]
            for o, (ny, nx) in zip(out, ((0, 0), (1, 0), (0, 1))):
                part = np.zeros(sel.shape)
                part[sel] = spline.ev(yy, xx, dx=ny, dy=nx)
                o[rows] = part
        return tuple(out)

    def variance_at(self, which, dy, dx):
        """The sampling variance of the residual at offsets ``(dy, dx)`` (fraction²).

        Interpolated linearly between the nodes (exact at the nodes; between them within
        about 10 % of the variance of :meth:`evaluate`'s spline, measured). Beyond the
        grid, 0. Arguments as :meth:`evaluate`.
        """
        from scipy.ndimage import map_coordinates

        which = np.asarray(which, int)
        out = np.zeros(dy.shape)
        inside = (np.abs(dy) <= self.extent) & (np.abs(dx) <= self.extent)
        for k in np.unique(which):
            rows = which == k
            sel = inside[rows]
            coords = (np.stack([dy[rows][sel], dx[rows][sel]]) + self.extent) * self.oversample
            part = np.zeros(sel.shape)
            part[sel] = map_coordinates(
                self.variance[k if len(self.variance) > 1 else 0], coords, order=1, mode="nearest"
            )
            out[rows] = part
        return out


@dataclass(frozen=True)
class BeadSearch:
    """What :func:`find_beads` found.

    Attributes
    ----------
    positions : ndarray, shape (n, 2), int
        (row, col) of the brightest pixel of every accepted bead, in row-major order.
    at_edge : ndarray, shape (m, 2), int
        Candidates rejected because their box would cross the image's edge.
    too_close : ndarray, shape (k, 2), int
        Candidates rejected because another candidate is nearer than ``min_separation``.
    threshold : float
        The detection threshold used, in the units of the image above its background.
    """

    positions: np.ndarray
    at_edge: np.ndarray
    too_close: np.ndarray
    threshold: float


def find_beads(image, *, width=1.0, half_size=4, min_separation=None, snr=8.0):
    """Find isolated bright spots: local maxima of the smoothed image above a noise threshold.

    Parameters
    ----------
    image : array_like, shape (R, C)
        Mean image of a stack, offset-subtracted or not (any unit: ADU or e⁻).
    width : float
        Expected spot standard deviation (pixel); the image is smoothed by half of it.
    half_size : int
        Half-width Δ of the fitting box (pixel): a bead must have Δ pixels on every side.
    min_separation : float, optional
        Two candidates nearer than this (pixel) are both rejected, since each would
        contaminate the other's box. Default ``2·half_size + 1``.
    snr : float
        Detection threshold in robust noise SDs (median absolute deviation of the smoothed
        image) above its median.

    Returns
    -------
    BeadSearch
    """
    img = np.asarray(image, float)
    if img.ndim != 2:
        raise OptionError(f"find_beads needs a 2-D image, got shape {img.shape}")
    if min_separation is None:
        min_separation = 2 * half_size + 1
    # Light smoothing (half the spot width) suppresses pixel noise but keeps two beads a
    # few pixels apart as two maxima.
    smooth = ndimage.gaussian_filter(img, 0.5 * width, mode="nearest")
    level = np.median(smooth)
    noise = 1.4826 * np.median(np.abs(smooth - level))
    if not noise > 0:  # a flat image has no robust spread; fall back on the plain SD
        noise = smooth.std()
    threshold = level + snr * noise if noise > 0 else np.inf
    # A 3×3 maximum filter keeps two nearby beads apart; noise maxima on one bead's flank
    # are merged into it below because no dip separates them.
    peaks = (smooth == ndimage.maximum_filter(smooth, size=3, mode="nearest")) & (
        smooth > threshold
    )
    cand = np.argwhere(peaks)
    height = smooth[tuple(cand.T)] - level
    keep = np.ones(len(cand), bool)
    close = np.zeros(len(cand), bool)
    for i in np.argsort(-height):  # brightest first: a flank maximum merges into its peak
        if not keep[i]:
            continue
        for j in np.flatnonzero(keep):
            dist = np.hypot(*(cand[j] - cand[i]))
            if j == i or dist >= min_separation:
                continue
            t = np.linspace(0.0, 1.0, max(3, int(4 * dist)))
            path = np.rint(cand[i] + t[:, None] * (cand[j] - cand[i])).astype(int)
            dip = smooth[tuple(path.T)].min() - level
            if dip < 0.8 * min(height[i], height[j]):
                close[[i, j]] = True  # two spots, each in the other's box
            else:
                keep[j] = False  # the same spot
    cand, close = cand[keep], close[keep]
    rows, cols = img.shape
    edge = (
        (
            (cand[:, 0] < half_size)
            | (cand[:, 1] < half_size)
            | (cand[:, 0] >= rows - half_size)
            | (cand[:, 1] >= cols - half_size)
        )
        if len(cand)
        else np.zeros(0, bool)
    )
    return BeadSearch(
        positions=cand[~edge & ~close],
        at_edge=cand[edge],
        too_close=cand[close & ~edge],
        threshold=float(threshold - level),
    )
