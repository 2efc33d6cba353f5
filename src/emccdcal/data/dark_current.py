"""Dark current from stacks at two or more exposures: each pixel's mean counts against
the exposure, a weighted straight line, its slope times φ.

The points are the 1× dark stacks behind a series' maps, at their ``dark_exposure_s``
(their mean is the offset map, its variance the map's own), and, on the photon-free path
(``light = false``: Diekmann et al. 2022, *Nat. Commun.* 13:3362), every stack of the
series, a dark at its ``exposure_s`` (the mean of its frames, its variance s²/n). A line
``mean = a + b·t`` fitted by weighted least squares gives b (ADU/s); the dark current is
``φ·b`` (e⁻ per pixel per second), its variance ``(φ·SE b)² + (b·SE φ)²`` (the slope from
the means, φ from the variances: their errors nearly independent). With three or more
points the line's χ² tests that the dark signal grows linearly with exposure and that the
offset does not move with it (``dark_current_pvalue``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import special

from ..defaults import DEFAULT_K
from .dark import map_variances, maps_from_dark
from .quality.drift import robust_spread


@dataclass(frozen=True)
class ExposurePoint:
    """One stack's mean counts at one exposure: ``mean`` and ``variance`` (of the mean)
    maps (ADU, ADU²), at ``exposure_s`` (s), named by ``label``."""

    exposure_s: float
    mean: np.ndarray
    variance: np.ndarray
    label: str


def exposure_points(acquisitions, light=True) -> list[ExposurePoint]:
    """The points of a series' 1× stacks: each distinct dark with a known exposure and
    frame count; on the photon-free path (``light`` False) also every acquisition's
    frames, read once more for their means."""
    points, seen = [], set()
    for a in acquisitions:
        if a.em_gain_setpoint != 1:
            continue
        key = (str(a.offset_source), a.dark_exposure_s)
        if a.dark_exposure_s is not None and a.dark_frames is not None and key not in seen:
            seen.add(key)
            variance, _ = map_variances(a.offset, a.read_noise, a.dark_frames, True)
            points.append(
                ExposurePoint(a.dark_exposure_s, a.offset, variance, str(a.offset_source))
            )
        if not light:
            mean, sd = maps_from_dark(a.frames())
            points.append(ExposurePoint(a.exposure_s, mean, sd**2 / a.n_frames, a.name))
    return points


def dark_current(points, e_per_adu, e_per_adu_se=None) -> dict | None:
    """Each pixel's dark current from its :class:`ExposurePoint` s.

    Parameters
    ----------
    points : list of ExposurePoint
        Two or more distinct exposures.
    e_per_adu, e_per_adu_se : ndarray (R, C)
        φ (e⁻/ADU) and its SE (None or NaN: taken as exact).

    Returns
    -------
    dict or None
        ``dark_current`` and ``dark_current_se`` (e⁻/s per pixel), ``adu_per_s`` (the
        slope, ADU/s), ``pvalue`` (the line's χ² with K − 2 degrees of freedom; None for
        two points); None where fewer than two distinct exposures are given.

    Examples
    --------
    >>> import numpy as np
    >>> pts = [ExposurePoint(t, np.array([[100.0 + 2.0 * t]]), np.array([[0.01]]), str(t))
    ...        for t in (0.1, 1.0, 2.0)]
    >>> out = dark_current(pts, np.array([[0.5]]))
    >>> float(out["dark_current"][0, 0]), out["pvalue"][0, 0] > 0.99
    (1.0, np.True_)
    """
    if len({p.exposure_s for p in points}) < 2:
        return None
    t = np.array([p.exposure_s for p in points])[:, None, None]
    y = np.stack([p.mean for p in points])
    w = 1.0 / np.stack([p.variance for p in points])
    s, sx, sy = w.sum(0), (w * t).sum(0), (w * y).sum(0)
    sxx, sxy = (w * t * t).sum(0), (w * t * y).sum(0)
    det = s * sxx - sx * sx
    slope = (s * sxy - sx * sy) / det
    intercept = (sy - sx * slope) / s
    slope_var = s / det
    phi = np.asarray(e_per_adu, dtype=float)
    phi_var = 0.0 if e_per_adu_se is None else np.nan_to_num(np.asarray(e_per_adu_se) ** 2)
    rate = phi * slope
    rate_se = np.sqrt(phi**2 * slope_var + slope**2 * phi_var)
    dof = len(points) - 2
    pvalue = None
    if dof > 0:
        chi2 = (w * (y - intercept - slope * t) ** 2).sum(0)
        pvalue = special.chdtrc(dof, chi2)  # chi2.sf, without importing scipy.stats
    return {"dark_current": rate, "dark_current_se": rate_se, "adu_per_s": slope, "pvalue": pvalue}


def hot_pixels(rate, rate_se, k=DEFAULT_K) -> tuple[np.ndarray, float] | None:
    """Hot pixels: a dark current more than ``k`` robust SDs above the median pixel's.

    The spread is 1.4826 × the median absolute deviation of the finite rates, or the
    median pixel's own standard error where that is larger (a sensor of near-equal
    pixels is not all hot and cold by its noise), as the data-quality checks find hot
    pixels in a stack's means. Of pixels whose dark currents are normal about their
    median, a fraction Q(k) (2.9e-7 at k = 5) is flagged by chance; of a log-normal
    population, more (0.7 % where ln of the rate has an SD of 0.5: above 3.4 times the
    median).

    Parameters
    ----------
    rate, rate_se : ndarray (R, C)
        Dark current and its SE (e⁻/s); NaN where not measured.
    k : float

    Returns
    -------
    (ndarray of bool (R, C), float) or None
        The flags and the threshold (e⁻/s); None with fewer than five measured pixels.

    Examples
    --------
    >>> rate = np.array([[1.0, 1.1, 0.9, 1.05], [0.95, 40.0, 1.0, np.nan]])
    >>> flags, threshold = hot_pixels(rate, np.full(rate.shape, 0.01))
    >>> flags.astype(int).tolist(), round(threshold, 2)
    ([[0, 0, 0, 0], [0, 1, 0, 0]], 1.37)
    """
    finite = np.isfinite(rate)
    if finite.sum() < 5:
        return None
    median, spread = robust_spread(rate[finite], float(np.nanmedian(rate_se[finite])))
    threshold = median + k * spread
    with np.errstate(invalid="ignore"):
        return finite & (rate > threshold), threshold
