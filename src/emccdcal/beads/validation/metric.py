"""The validation's metric and what moves a bead's intensity besides the calibration: the consistency of the mean intensities across set-points (:func:`consistency`), a trend over the frames (:func:`intensity_trend`: bleaching) and blinking (:func:`blinking_level`); the files and thresholds a validation uses."""

from __future__ import annotations

import math
import warnings
from typing import NamedTuple

import numpy as np

from ... import result
from ...errors import InputError, OptionError


VALIDATION_FILE = "validation.json"
INTENSITIES_FILE = "intensities.nc"
#: ddof of the headline consistency metric (ddof = 1 is reported beside it).
DDOF = 0
#: Below this fraction of converged frames at a set-point, validate warns.
MIN_CONVERGED = 0.99
#: An intensity trend (bleaching) is detected beyond this many of its standard errors.
TREND_Z = 4.0
#: What validate does with a detected trend.
TREND_ACTIONS = ("correct", "warn")
#: Spot models of validate: the Gaussian alone, or with the residual image of each bead
#: or of all beads pooled (the paper's second pass).
PSF_MODELS = ("gaussian", "residual", "residual-pooled")
#: Above this χ² per pixel of a set-point's mean residual (the spot model against the
#: beads' mean images), validate says the PSF is not the Gaussian. Under a right model
#: it is about 1; for 81 pixels, 2 has a chance of about 1e-7.
PSF_CHI2 = 2.0
#: What validate does with blinking beads.
BLINK_ACTIONS = ("model", "ignore")
#: Blinking is detected at a bead's set-point where the two-level mixture beats one level
#: by this much (2 Δ ln L): a chance of 1e-4 without blinking (half χ²₁ at the boundary).
BLINK_LR = 13.83


# --------------------------------------------------------------------------------------
# The metric
# --------------------------------------------------------------------------------------
def consistency(means, *, ddof=DDOF):
    """Spread of one bead's per-set-point mean intensities, scaled to its 1× mean.

    Parameters
    ----------
    means : mapping of float to float
        Set-point -> mean intensity over frames (e⁻); must include set-point 1.
    ddof : int
        Delta degrees of freedom of the standard deviation (0: population SD).

    Returns
    -------
    incl, excl : float
        SD of ``m_k / m_1`` over all set-points, and over those other than 1
        (dimensionless); NaN when there are not more than ``ddof`` values or a mean is
        not finite.

    Examples
    --------
    docs/validation.md case 14:

    >>> m = {1: 1.00, 5: 1.10, 25: 0.99, 100: 1.01, 300: 1.00}
    >>> [round(v, 6) for v in consistency(m)], [round(v, 6) for v in consistency(m, ddof=1)]
    ([0.040497, 0.043875], [0.045277, 0.050662])
    """
    m = {float(k): float(v) for k, v in means.items()}
    if 1.0 not in m:
        raise OptionError("the consistency metric is scaled to the 1x mean: set-point 1 is needed")
    ref = m[1.0]
    scaled = {k: v / ref for k, v in m.items()} if ref != 0 else {k: math.nan for k in m}

    def sd(values):
        v = np.array(values, dtype=float)
        if v.size <= ddof or not np.all(np.isfinite(v)):
            return math.nan
        return float(np.std(v, ddof=ddof))

    return sd(list(scaled.values())), sd([v for k, v in scaled.items() if k != 1.0])


# --------------------------------------------------------------------------------------
# validate
# --------------------------------------------------------------------------------------
def _acquisitions_by_setpoint(manifest):
    """The acquisitions at each set-point, in the manifest's (recording) order: a set-point
    recorded again (1× at the start and at the end of a series) has several."""
    by = {}
    for a in manifest.acquisitions:
        by.setdefault(float(a.em_gain_setpoint), []).append(a)
    if 1.0 not in by:
        raise InputError(
            f"{manifest.path}: no acquisition at set-point 1; the consistency metric is "
            "scaled to each bead's 1x mean intensity"
        )
    return dict(sorted(by.items()))


class _Slot(NamedTuple):
    """Where one acquisition's frames go in the (set-point, frame) arrays."""

    row: int  # the row of its set-point
    setpoint: float
    acq: object  # the manifest's Acquisition
    first: int  # its first column: a repeated set-point's frames follow the earlier ones
    key: str  # label: the set-point, "#2" for its second acquisition …
    start: int  # frames recorded before it in the series


def _frame_layout(manifest, acqs):
    """One :class:`_Slot` per acquisition, in the manifest's (recording) order."""
    rows = {s: i for i, s in enumerate(acqs)}
    used = dict.fromkeys(acqs, 0)
    count = dict.fromkeys(acqs, 0)
    layout, t0 = [], 0
    for a in manifest.acquisitions:
        s = float(a.em_gain_setpoint)
        count[s] += 1
        key = result.format_setpoint(s) + ("" if count[s] == 1 else f"#{count[s]}")
        layout.append(_Slot(rows[s], s, a, used[s], key, t0))
        used[s] += a.n_frames
        t0 += a.n_frames
    return layout


def _frame_times(layout, S, F):
    """Each frame's place in the recorded series (frames since the first), shape (S, F)."""
    times = np.zeros((S, F))
    for slot in layout:
        n = slot.acq.n_frames
        times[slot.row, slot.first : slot.first + n] = slot.start + np.arange(n)
    return times


def intensity_trend(N, se, times, *, z_detect=TREND_Z) -> dict:
    """The beads' common intensity trend within acquisitions: bleaching (or a drifting
    illumination), which would otherwise look like a gain error between set-points.

    Every bead's intensity at a set-point is compared with its own mean there, so the
    levels of the set-points (what the gains set) do not enter; the rate is the weighted
    least-squares slope, common to all beads, of ``N_f / m − 1`` against the frame's time
    in the series, ``N_f ≈ m (1 − k (t − t̄))``.

    Parameters
    ----------
    N, se : ndarray, shape (B, S, F)
        Per-frame intensities and their SEs (e⁻), NaN where a frame is not used.
    times : ndarray, shape (S, F)
        Each frame's place in the series (frames).

    Returns
    -------
    dict
        ``rate_per_frame`` k (1/frame, > 0 for a fade) and its ``rate_se`` (scaled by the
        scatter where it exceeds the errors), ``z``, ``fade_over_series`` (1 − e^(−k T)
        over the T frames recorded) and ``detected`` (|z| > ``z_detect``).
    """
    ok = np.isfinite(N) & np.isfinite(se) & (se > 0)
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        m = np.nanmean(np.where(ok, N, np.nan), axis=2, keepdims=True)
        t = np.broadcast_to(times, N.shape)
        w = np.where(ok & (m > 0), (m / np.where(ok, se, 1.0)) ** 2, 0.0)
        y = np.where(w > 0, N / m - 1, 0.0)
        sw = w.sum(axis=2, keepdims=True)
        use = sw > 0
        tbar = np.where(use, (w * t).sum(axis=2, keepdims=True) / np.where(use, sw, 1), 0)
        ybar = np.where(use, (w * y).sum(axis=2, keepdims=True) / np.where(use, sw, 1), 0)
        x, yc = t - tbar, y - ybar
        sxx = float((w * x * x).sum())
    if sxx <= 0:
        return {
            "rate_per_frame": None,
            "rate_se": None,
            "z": None,
            "fade_over_series": None,
            "detected": False,
        }
    k = -float((w * x * yc).sum()) / sxx
    chi2 = float((w * (yc + k * x) ** 2).sum())
    dof = int((w > 0).sum()) - int(use.sum()) - 1
    rate_se = math.sqrt(max(1.0, chi2 / dof) / sxx) if dof > 0 else math.sqrt(1 / sxx)
    span = float(np.nanmax(times) - np.nanmin(times))
    z = k / rate_se
    return {
        "rate_per_frame": k,
        "rate_se": rate_se,
        "z": z,
        "fade_over_series": -math.expm1(-k * span),
        "detected": bool(abs(z) > z_detect),
    }


def blinking_level(N, se, *, lr_detect=BLINK_LR, iterations=200) -> dict:
    """Beads that switch off: each bead's intensities at a set-point as a mixture of an
    "on" level and zero.

    A blinking bead emits nothing in some frames, which lowers its mean at that set-point
    by the fraction of frames it was off: a different fraction at every set-point, which
    the metric would take for gain errors. Each frame's intensity is modelled as
    ``N_f ~ (1 − f)·Normal(m, se_f) + f·Normal(0, se_f)`` with its own standard error, and
    m and the off fraction f are fitted by expectation–maximisation. Where the mixture
    beats one level (``f = 0``) by ``2 Δ ln L > lr_detect``, blinking is detected and the
    on level ``Σ (1 − r_f) N_f / Σ (1 − r_f)`` (``r_f`` the frame's probability of being
    off) replaces the mean. A frame is counted as off where ``r_f > ½``. A bead dimmed
    rather than off in some frames (a partial blink within an exposure) is not what the
    model describes.

    Parameters
    ----------
    N, se : ndarray, shape (..., F)
        Per-frame intensities and standard errors (e⁻), NaN where a frame is not used.

    Returns
    -------
    dict
        ``on_level`` (...) e⁻, ``off_fraction`` (...), ``lr`` (...) the statistic,
        ``detected`` (...) bool, ``off_probability`` (..., F) and ``off`` (..., F) bool
        (False where not detected).

    Examples
    --------
    >>> rng = np.random.default_rng(3)
    >>> on = rng.random((1, 400)) > 0.1
    >>> N = np.where(on, 5000.0, 0.0) + 50.0 * rng.standard_normal((1, 400))
    >>> b = blinking_level(N, np.full((1, 400), 50.0))
    >>> bool(b["detected"][0]), int(b["off"].sum()) == int((~on).sum())
    (True, True)
    >>> bool(abs(b["on_level"][0] - 5000) < 10)
    True
    """
    ok = np.isfinite(N) & np.isfinite(se) & (se > 0)
    x = np.where(ok, N, 0.0)
    w = np.where(ok, 1.0 / np.where(ok, se, 1.0) ** 2, 0.0)
    n = ok.sum(axis=-1)

    def e_step(m, f):
        """Each frame's log-likelihood under the mixture, and its probability of being off."""
        l_on = np.log1p(-f)[..., None] - 0.5 * w * (x - m[..., None]) ** 2
        l_off = np.log(f)[..., None] - 0.5 * w * x**2
        l_mix = np.logaddexp(l_on, l_off)
        return l_mix, np.where(ok, np.exp(l_off - l_mix), 0.0)

    with np.errstate(invalid="ignore", divide="ignore"):
        m1 = (w * x).sum(axis=-1) / w.sum(axis=-1)  # one level: weighted ML mean
        ll_one = np.where(ok, -0.5 * w * (x - m1[..., None]) ** 2, 0.0).sum(axis=-1)
        m, f = m1.copy(), np.full(m1.shape, 0.1)
        for _ in range(iterations):
            _, r = e_step(m, f)
            f = np.clip(r.sum(axis=-1) / n, 1e-9, 1 - 1e-9)
            m = ((1 - r) * w * x).sum(axis=-1) / ((1 - r) * w).sum(axis=-1)
        l_mix, r = e_step(m, f)
        lr = 2.0 * (np.where(ok, l_mix, 0.0).sum(axis=-1) - ll_one)
        detected = np.isfinite(lr) & (lr > lr_detect) & (n > 1)
    on_level = _on_level(np.where(ok, N, np.nan), r)
    return {
        "on_level": on_level,
        "off_fraction": np.where(detected, f, 0.0),
        "lr": lr,
        "detected": detected,
        "off_probability": np.where(detected[..., None], r, 0.0),
        "off": detected[..., None] & (r > 0.5),
    }


def _on_level(N, off_probability):
    """``Σ (1 − r_f) N_f / Σ (1 − r_f)`` over the frames where N is finite, shape (...)."""
    on = np.where(np.isfinite(N), 1.0 - off_probability, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.nansum(on * N, axis=-1) / on.sum(axis=-1)
