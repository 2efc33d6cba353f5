"""Bead validation: does a calibration give every bead the same intensity at every set-point?

The paper's independent test of a calibration (Ryan et al. 2021, Figs. 4–5;
docs/beads.md). Beads are imaged at every gain set-point; their photoelectron count per frame does
not depend on the camera's gain, so under a correct calibration (φ and the gain at every
set-point) the fitted intensities agree across set-points. Under a wrong gain g' at a
set-point the intensities there are scaled by about g/g'.

For bead b, set-point k and frame f, let N_bkf be the fitted intensity (e⁻,
:func:`emccdcal.beads.fit.fit_beads`) and m_bk its mean over the converged frames. The metric
is the spread of a bead's per-set-point means, scaled to its 1× mean:

    σ_means,incl(b) = std_k { m_bk / m_b1 : all set-points }
    σ_means,excl(b) = std_k { m_bk / m_b1 : set-points other than 1× }

(dimensionless; lower is better). The headline uses **ddof = 0** (the population SD of
the set-points' means; the paper does not say which it used) and ``validation.json``
reports ddof = 1 beside it. A calibration's value is the mean over its beads. Because the
1× intensities depend only on φ, the metric tests each gain against the 1× anchor.

Each calibration's beads are fitted twice: at every set-point with each bead's shape and
background shared by its frames, then again with each bead's width pooled over the
set-points (:func:`emccdcal.beads.fit.shared_widths`), so that a width error cannot
differ between set-points; the second pass gives the intensities (or, with ``psf=
"residual"``, a third pass with each bead's oversampled residual image added to the
spot: the paper's second pass, the image built on one half of the frames and its fit
scored on the other). ``converged_fraction`` says per set-point how many frames
converged, and below 99 % a warning says so.

What real beads do besides is measured, reported and, by default, undone before the
set-points are compared: bleaching (:func:`intensity_trend`, from the frames' own time
course and from a set-point recorded more than once), blinking (:func:`blinking_level`:
the "on" level of a two-level mixture), and a PSF that the Gaussian does not describe
(``psf_mismatch``, with a warning).

``emccdcal validate BEAD_MANIFEST --calibration A.nc [--calibration B.nc ...] -o OUT``
fits the beads under every calibration and writes ``OUT/validation.json``,
``OUT/intensities.nc`` and the figures; ``docs/beads.md`` describes them.

Calibrations
------------
A ``--calibration`` is a calibration result (``calibration.nc`` or its directory) or a
comma-joined group of them whose set-points are merged into one calibration: φ from the
member that measured it (``is-adu`` or ``mv-adu``; else from the first member) and the
gain at each set-point from the member that has it (``is-gain`` results hold one
set-point each). The gain at 1× is 1 by definition, so a calibration needs a gain for
every other set-point of the bead manifest. Pixels that did not converge count as
missing; a bead whose box has a missing value is left out for that calibration.
"""

from __future__ import annotations

import datetime as _dt
import functools
import json
import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .. import _files, identity, result
from .._output import atomic_write, atomic_write_text, read_netcdf, write_netcdf
from .._util import finite_or_none
from .._util import progress as progress_bar
from ..data.manifest import Manifest, read_manifest
from ..errors import BeadWarning, InputError, MissingFileError, OptionError
from . import fit as bead_fit

__all__ = [
    "VALIDATION_FILE",
    "INTENSITIES_FILE",
    "DDOF",
    "consistency",
    "intensity_trend",
    "blinking_level",
    "validate",
    "fit_validation",
    "validation_document",
    "BeadFits",
    "read_validation",
    "format_table",
    "data_checks",
]

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


def _detect(manifest, acqs, setpoint, width, half_size, min_separation, snr):
    s = max(acqs) if setpoint is None else float(setpoint)
    if s not in acqs:
        raise OptionError(
            f"{manifest.path}: no acquisition at set-point "
            f"{result.format_setpoint(s)}x to detect the beads on"
        )
    acq = acqs[s][0]
    found = bead_fit.detect_beads(
        acq.frames(),
        acq.offset,
        width=width,
        half_size=half_size,
        min_separation=min_separation,
        snr=snr,
    )
    where = f"{acq.frames_path} (mean image, threshold {found.threshold:.4g} ADU above background)"
    if len(found.at_edge):
        warnings.warn(
            f"{acq.frames_path}: skipped {len(found.at_edge)} bead(s) closer than {half_size} px "
            f"to the frame's edge at (row, col) {_pairs(found.at_edge)}",
            stacklevel=3,
            category=BeadWarning,
        )
    if len(found.too_close):
        warnings.warn(
            f"{acq.frames_path}: skipped {len(found.too_close)} bead(s) with another bead "
            f"inside their fitting box at (row, col) {_pairs(found.too_close)}",
            stacklevel=3,
            category=BeadWarning,
        )
    if len(found.positions) == 0:
        n_cand = len(found.at_edge) + len(found.too_close)
        if n_cand:
            raise InputError(
                f"{where}: all {n_cand} bead(s) found are at the edge or too close to another "
                "bead; none left to fit"
            )
        raise InputError(f"{where}: no beads found")
    return found, acq


def _pairs(arr, limit=6):
    items = [f"({int(r)}, {int(c)})" for r, c in np.asarray(arr)[:limit]]
    more = f" and {len(arr) - limit} more" if len(arr) > limit else ""
    return ", ".join(items) + more


def _box_ok(phi, gain, positions, half_size):
    """Beads whose whole box has a usable φ (finite, > 0) and gain (finite, >= 1)."""
    ok = np.ones(len(positions), bool)
    for i, (r, c) in enumerate(positions):
        box = (slice(r - half_size, r + half_size + 1), slice(c - half_size, c + half_size + 1))
        p, g = phi[box], gain[box]
        ok[i] = bool(np.all(np.isfinite(p) & (p > 0)) and np.all(np.isfinite(g) & (g >= 1)))
    return ok


@dataclass
class _Fitted:
    """Every bead fit of a validation, arrays (calibration, bead, set-point, frame).

    ``arr`` and ``arr_se`` map each parameter of :data:`emccdcal.model.psf.PARAMETERS`
    to its values and standard errors (NaN where a frame does not exist or a bead was left out);
    ``offset_se`` (calibration, bead, set-point) is the error of each bead's mean
    intensity from the offset maps (e⁻), ``shared_se`` that from its shared parameters'
    error (position, width, background; :attr:`BeadFits.intensity_shared_se`), both
    common to its frames; ``mismatch`` per calibration the PSF checks of
    each spot model (:func:`emccdcal.beads.fit.psf_mismatch`) per acquisition.
    """

    arr: dict
    arr_se: dict
    loglik: np.ndarray
    conv: np.ndarray
    offset_se: np.ndarray
    shared_se: np.ndarray
    mismatch: list


def validate(
    bead_manifest,
    calibrations,
    *,
    out=None,
    width=bead_fit.DEFAULT_WIDTH,
    half_size=bead_fit.DEFAULT_HALF_SIZE,
    min_separation=None,
    snr=8.0,
    detect_setpoint=None,
    progress=True,
    bleaching="correct",
    psf="gaussian",
    blinking="model",
    psf_split="alternate",
    accept_mismatch=(),
) -> dict:
    """Fit the beads under each calibration and compare their intensities across set-points.

    Parameters
    ----------
    bead_manifest : str, Path or :class:`emccdcal.Manifest`
        Manifest of the bead stacks: one acquisition per set-point, 1× included, each with
        its offset and read-noise maps (or darks).
    calibrations : sequence of (str, Path or sequence)
        Calibration results; each item is a file (or directory) or a comma-joined group
        merged by :func:`emccdcal.result.load_calibration`.
    out : str or Path, optional
        Directory to write ``validation.json`` and ``intensities.nc`` into (the figures:
        :func:`emccdcal.report.figures.write_validation_figures`).
    width : float
        Expected PSF SD (pixel): detection and starting value.
    half_size : int
        Fitting box half-width Δ (pixel).
    min_separation : float, optional
        Least distance between beads (pixel; default 2Δ + 1).
    snr : float
        Detection threshold in robust noise SDs.
    detect_setpoint : float, optional
        Set-point whose mean image the beads are found on (default the highest).
    progress : bool
        A progress bar (default): in a notebook or on a terminal; none in a pipe.
    bleaching : {"correct", "warn"}
        What to do where the beads' intensity trends within the acquisitions
        (:func:`intensity_trend`: bleaching, or a drifting illumination): undo it (each
        frame's intensity times e^(k t), t its place in the series, the acquisitions in
        the manifest's order) before the means are compared, or only warn. Either way
        ``validation.json`` reports it (``intensity_trend``).
    psf : {"gaussian", "residual", "residual-pooled"}
        The spot model: the pixel-integrated Gaussian (default), or the paper's second
        pass: a third fit with each bead's oversampled residual image added to it
        (:func:`emccdcal.beads.fit.residual_image`; "residual-pooled": one image for all
        beads). Either way ``psf_mismatch`` in ``validation.json`` says how well the
        Gaussian describes the beads' mean images, with a warning where it does not.
    psf_split : {"alternate", "time"}
        With a residual image: it is built from one half of every acquisition's frames
        and its goodness of fit scored on the other (:func:`emccdcal.beads.fit.frame_halves`:
        even and odd frames, or the first and second half in time), so that the score
        is on data the image has not seen; ``validation.json`` says which
        (``psf_held_out``).
    blinking : {"model", "ignore"}
        Beads that switch off for some frames (:func:`blinking_level`): at a set-point
        where a bead's intensities are a mixture of an "on" level and zero, take the on
        level rather than the mean (default), or ignore blinking (the plain mean). Either
        way ``validation.json`` reports the frames found off (``blinking``).
    accept_mismatch : iterable of str
        Identity fields (:data:`emccdcal.identity.ACCEPTABLE`) in which the bead frames
        may differ from a calibration: by default a calibration of another camera or
        read-out state is refused.

    Returns
    -------
    dict
        The content of ``validation.json`` (``docs/beads.md``).

    Raises
    ------
    FileNotFoundError, ValueError (emccdcal.InputError)
        Unknown files, a calibration of another sensor size or region, a set-point of the
        bead data missing from a calibration, no beads found (or none left after the edge
        and crowding checks). All checked before any fitting.

    Examples
    --------
    Beads simulated at every set-point of a calibration, tested against it (the gallery
    has the whole example, with its figures):

    >>> import tempfile, emccdcal
    >>> work = tempfile.mkdtemp()
    >>> beads = emccdcal.simulate_beads(f"{work}/beads", beads=6, seed=1)  # doctest: +SKIP
    >>> found = emccdcal.validate(
    ...     beads.manifest, [beads.outdir / "truth_calibration.nc"]
    ... )  # doctest: +SKIP
    """
    _check_actions(bleaching, blinking)
    fits = fit_validation(
        bead_manifest,
        calibrations,
        width=width,
        half_size=half_size,
        min_separation=min_separation,
        snr=snr,
        detect_setpoint=detect_setpoint,
        progress=progress,
        psf=psf,
        psf_split=psf_split,
        accept_mismatch=accept_mismatch,
    )
    doc = validation_document(fits, bleaching=bleaching, blinking=blinking)
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        ds = _intensities_dataset(
            fits.cals, fits.setpoints, fits.positions, fits.fitted, fits.manifest, fits.layout
        )
        atomic_write(out / INTENSITIES_FILE, lambda p: write_netcdf(ds, p))
        text = json.dumps(doc, indent=2, allow_nan=False) + "\n"
        atomic_write_text(out / VALIDATION_FILE, text)
    return doc


def _check_actions(bleaching, blinking) -> None:
    if bleaching not in TREND_ACTIONS:
        raise OptionError(f"bleaching must be one of {', '.join(TREND_ACTIONS)}; got {bleaching!r}")
    if blinking not in BLINK_ACTIONS:
        raise OptionError(f"blinking must be one of {', '.join(BLINK_ACTIONS)}; got {blinking!r}")


@dataclass
class BeadFits:
    """What :func:`fit_validation` fitted: everything :func:`validation_document` needs to
    compare the calibrations, whatever it is told to do with bleaching and blinking."""

    manifest: Manifest
    cals: list
    setpoints: list
    positions: np.ndarray
    fitted: _Fitted
    layout: list
    detected_on: object
    half_size: int
    psf: str
    seconds: float
    psf_split: str = "alternate"


def fit_validation(
    bead_manifest,
    calibrations,
    *,
    width=bead_fit.DEFAULT_WIDTH,
    half_size=bead_fit.DEFAULT_HALF_SIZE,
    min_separation=None,
    snr=8.0,
    detect_setpoint=None,
    progress=True,
    psf="gaussian",
    psf_split="alternate",
    accept_mismatch=(),
) -> BeadFits:
    """The fitting half of :func:`validate` (same parameters): find the beads and fit
    them under every calibration. :func:`validation_document` then compares them, as
    often as asked (bleaching corrected or not, blinking modelled or not), without
    fitting again."""
    t0 = time.perf_counter()
    if psf not in PSF_MODELS:
        raise OptionError(f"psf must be one of {', '.join(PSF_MODELS)}; got {psf!r}")
    if psf_split not in bead_fit.RESIDUAL_SPLITS:
        raise OptionError(
            f"psf_split must be one of {', '.join(bead_fit.RESIDUAL_SPLITS)}; got {psf_split!r}"
        )
    manifest = (
        bead_manifest if isinstance(bead_manifest, Manifest) else read_manifest(bead_manifest)
    )
    if not calibrations:
        raise OptionError("give at least one calibration to validate")
    acqs = _acquisitions_by_setpoint(manifest)
    setpoints = list(acqs)
    cals = [result.load_calibration(c, manifest.shape, of="the bead frames") for c in calibrations]
    seen: dict = {}
    for cal in cals:  # a calibration given twice would be ranked against itself
        if cal.sha256 in seen:
            raise OptionError(
                f"calibration {cal.label} is given twice (also as "
                f"{seen[cal.sha256]}); give each once"
            )
        seen[cal.sha256] = cal.label
    for cal in cals:
        identity.check(
            cal.identity(),
            {manifest.path: manifest.identity()},
            label=cal.label,
            accept=accept_mismatch,
            what="bead frames",
        )
        for s in setpoints:
            cal.gain(s)  # raises for a missing set-point, before any fitting
    found, det_acq = _detect(manifest, acqs, detect_setpoint, width, half_size, min_separation, snr)
    positions = found.positions
    layout = _frame_layout(manifest, acqs)
    fitted = _fit_all(
        manifest,
        cals,
        setpoints,
        positions,
        layout,
        acqs,
        width=width,
        half_size=half_size,
        psf=psf,
        psf_split=psf_split,
        progress=progress,
    )
    return BeadFits(
        manifest,
        cals,
        setpoints,
        positions,
        fitted,
        layout,
        det_acq,
        half_size,
        psf,
        time.perf_counter() - t0,
        psf_split,
    )


def validation_document(fits: BeadFits, *, bleaching="correct", blinking="model") -> dict:
    """The content of ``validation.json`` from :func:`fit_validation`'s fits (the
    comparing half of :func:`validate`; ``bleaching`` and ``blinking`` as there), with
    its warnings."""
    _check_actions(bleaching, blinking)
    return _summarise(
        fits.manifest,
        fits.cals,
        fits.setpoints,
        fits.positions,
        fits.fitted,
        fits.layout,
        fits.detected_on,
        fits.half_size,
        fits.seconds,
        bleaching=bleaching,
        blinking=blinking,
        psf=fits.psf,
        psf_split=fits.psf_split,
    )


def _fit_all(
    manifest,
    cals,
    setpoints,
    positions,
    layout,
    acqs,
    *,
    width,
    half_size,
    psf,
    psf_split,
    progress,
) -> _Fitted:
    """Fit the beads of every acquisition under every calibration: with the width free,
    again with each bead's width pooled over set-points, and (``psf`` other than
    "gaussian") a third time with the residual image added, the image built on one half
    of the frames (``psf_split``) and scored on the other."""
    B, S, A = len(positions), len(setpoints), len(layout)
    Fmax = max(sum(a.n_frames for a in group) for group in acqs.values())
    names = ("x", "y", "width", "intensity", "background")
    shape = (len(cals), B, S, Fmax)
    arr = {n: np.full(shape, np.nan) for n in names}
    arr_se = {n: np.full(shape, np.nan) for n in names}
    loglik = np.full(shape, np.nan)
    conv = np.zeros(shape, bool)
    # Σ over a set-point's acquisitions of (frames × offset-map SE of the bead's mean)²
    offset_var = np.zeros(shape[:3])
    shared_var = np.zeros(shape[:3])  # the same for the shared parameters' error
    cache: dict = {}

    def fit_at(cal, j, ok, fixed=None, residual=None, fixed_se=None):
        """The beads ``ok`` in acquisition ``j`` of the layout under ``cal`` (cached:
        calibrations that agree there share the fit); ``fixed`` widths with their SE."""
        acq, g = layout[j].acq, cal.gain(layout[j].setpoint)
        boxes = [_boxes_bytes(m, positions[ok], half_size) for m in (cal.e_per_adu, g)]
        extras = [None if x is None else x.tobytes() for x in (fixed, fixed_se)]
        key = (
            j,
            positions[ok].tobytes(),
            *boxes,
            cal.em_model,
            *extras,
            None if residual is None else residual.values.tobytes(),
            psf_split,
        )
        if key not in cache:
            # the offset map's own error: the dark frames' SD over their square root
            offset_se = (
                None
                if not acq.dark_frames
                else np.asarray(acq.read_noise) / math.sqrt(acq.dark_frames)
            )
            cache[key] = bead_fit.fit_beads(
                acq.frames(),
                positions[ok],
                offset=acq.offset,
                read_noise=acq.read_noise,
                e_per_adu=cal.e_per_adu,
                em_gain=g,
                half_size=half_size,
                width=width,
                adc_max=manifest.adc_max,
                em_model=cal.em_model,
                fixed_width=fixed,
                fixed_width_se=fixed_se,
                residual=residual,
                offset_se=offset_se,
                residual_split=psf_split,
            )
        return cache[key]

    passes = 2 if psf == "gaussian" else 3
    mismatch = []
    with progress_bar(
        enabled=progress, desc="fitting beads", unit="stack", total=passes * len(cals) * A
    ) as bar:
        for ci, cal in enumerate(cals):
            ok = _usable_beads(cal, setpoints, positions, half_size)
            fits, found = _passes(functools.partial(fit_at, cal), cal.method, ok, layout, psf, bar)
            mismatch.append(found)
            idx = np.flatnonzero(ok)
            for slot, fit in zip(layout, fits):
                at = (ci, idx, slot.row, slice(slot.first, slot.first + slot.acq.n_frames))
                for j, n in enumerate(names):
                    arr[n][at] = fit.params[..., j]
                    arr_se[n][at] = fit.se[..., j]
                loglik[at] = fit.loglik
                conv[at] = fit.converged
                frames_used = fit.converged.sum(axis=1)
                offset_var[ci, idx, slot.row] += (
                    frames_used * np.nan_to_num(fit.intensity_offset_se)
                ) ** 2
                shared_var[ci, idx, slot.row] += (
                    frames_used * np.nan_to_num(fit.intensity_shared_se)
                ) ** 2
                if fit.n_saturated and ci == 0:
                    warnings.warn(
                        f"{slot.acq.frames_path}: {fit.n_saturated} count(s) at the ADC "
                        "maximum in the bead boxes were left out of the fits",
                        stacklevel=2,
                        category=BeadWarning,
                    )

    with np.errstate(invalid="ignore", divide="ignore"):
        offset_se = np.sqrt(offset_var) / conv.sum(axis=3)
        shared_se = np.sqrt(shared_var) / conv.sum(axis=3)
    return _Fitted(arr, arr_se, loglik, conv, offset_se, shared_se, mismatch)


def _passes(fit_at, method, ok, layout, psf, bar):
    """The fits of one calibration's beads ``ok`` in every acquisition of the layout
    (``fit_at(j, ok, widths, image, fixed_se=)``), in two passes or three, and how well
    the PSF model fits them: ``(fits, mismatch)``."""
    # Pass 1: each acquisition with the width free (shared by its frames); the
    # widths pooled over set-points are every bead's one width for pass 2.
    first = []
    for j, slot in enumerate(layout):
        bar.set_postfix_str(f"{method} {slot.key}x (width)")
        first.append(fit_at(j, ok))
        bar.update(1)
    widths, widths_se = bead_fit.shared_widths(first, with_se=True)
    if not np.isfinite(widths).all():
        widths = None
    fits = []
    for j, slot in enumerate(layout):
        bar.set_postfix_str(f"{method} {slot.key}x")
        fits.append(fit_at(j, ok, widths, fixed_se=widths_se) if widths is not None else first[j])
        bar.update(1)
    gaussian = [bead_fit.psf_mismatch(f) for f in fits]
    if psf != "gaussian":  # the paper's second pass: the residual image added,
        # built on half 0 of the frames; half 1 scores it (psf_mismatch below)
        image = bead_fit.residual_image(fits, per_bead=psf == "residual", half=0)
        fits = []
        for j, slot in enumerate(layout):
            bar.set_postfix_str(f"{method} {slot.key}x (residual)")
            fits.append(fit_at(j, ok, widths, image, fixed_se=widths_se))
            bar.update(1)
    return fits, {"gaussian": gaussian} | (
        {}
        if psf == "gaussian"
        else {psf: [bead_fit.psf_mismatch(f, half=1, image=image) for f in fits]}
    )


def _usable_beads(cal, setpoints, positions, half_size) -> np.ndarray:
    """Which beads have a usable φ (> 0) and gain (≥ 1) in their box at every set-point
    under ``cal``; a warning names the others, left out for this calibration."""
    ok = np.ones(len(positions), bool)
    for s in setpoints:
        bad = ~_box_ok(cal.e_per_adu, cal.gain(s), positions, half_size)
        if bad.any():
            warnings.warn(
                f"{cal.label}: no usable e_per_adu (> 0) or gain (>= 1) at "
                f"{result.format_setpoint(s)}x in the box of {int(bad.sum())} bead(s) "
                f"at (row, col) {_pairs(positions[bad])}; left out for this calibration",
                stacklevel=3,
                category=BeadWarning,
            )
        ok &= ~bad
    return ok


def _boxes_bytes(m, positions, half_size):
    return b"".join(
        np.ascontiguousarray(
            m[r - half_size : r + half_size + 1, c - half_size : c + half_size + 1]
        ).tobytes()
        for r, c in positions
    )


def _summarise(
    manifest,
    cals,
    setpoints,
    positions,
    fitted,
    layout,
    det_acq,
    half_size,
    seconds,
    *,
    bleaching,
    blinking,
    psf,
    psf_split="alternate",
) -> dict:
    """The content of ``validation.json``: per calibration its beads' mean intensities at
    every set-point and the consistency metric, ranked (most consistent first)."""
    keys = [result.format_setpoint(s) for s in setpoints]
    times = _frame_times(layout, len(setpoints), fitted.conv.shape[-1])
    entries = []
    for ci, cal in enumerate(cals):  # a loop, not a comprehension: warnings' stack levels
        entries.append(
            _calibration_entry(
                cal,
                ci,
                keys,
                setpoints,
                positions,
                fitted,
                layout,
                times,
                bleaching=bleaching,
                blinking=blinking,
                psf=psf,
            )
        )
    order = sorted(
        range(len(entries)),
        key=lambda i: (
            entries[i]["sigma_means_incl_1x"] is None,
            entries[i]["sigma_means_incl_1x"]
            if entries[i]["sigma_means_incl_1x"] is not None
            else 0.0,
        ),
    )
    from .. import __version__

    return {
        "calibrations": entries,
        "ranking": [entries[i]["file"] for i in order],
        "ranking_by": "sigma_means_incl_1x (ascending: most consistent first)",
        "ddof": DDOF,
        "metric": (
            "per bead: SD over set-points of the bead's mean intensity (over converged frames) "
            "at each set-point divided by its 1x mean; dimensionless. incl_1x: all set-points; "
            "excl_1x: without 1x. Headline keys use ddof = 0, *_ddof1 keys ddof = 1. A "
            "calibration's value is the mean over its beads."
        ),
        "setpoints": keys,
        "units": {
            "mean_intensity": "e- per frame (whole bead)",
            "mean_intensity_se": "e-",
            "sigma_means": "1 (fraction of the 1x mean)",
            "row": "pixel",
            "col": "pixel",
        },
        "bead_manifest": str(manifest.path),
        "bead_manifest_sha256": manifest.content_hash,
        "detected_on": str(det_acq.frames_path),
        "half_size": int(half_size),
        **({} if psf == "gaussian" else {"psf_held_out": held_out_description(psf_split)}),
        "emccdcal_version": __version__,
        "created": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "seconds": finite_or_none(seconds),
    }


def held_out_description(split) -> dict:
    """What a residual image was built on and what scored it (``validation.json``'s
    ``psf_held_out``)."""
    built, scored = {
        "alternate": ("even frames", "odd frames"),
        "time": ("first half of the frames", "second half of the frames"),
    }[split]
    return {
        "split": split,
        "image_built_on": built,
        "scored_on": scored,
        "note": "the residual model's chi2_per_pixel is on frames the image has not "
        "seen, its own sampling variance included: about 1 (± chi2_per_pixel_se) "
        "where it describes the spot",
    }


def _calibration_entry(
    cal, ci, keys, setpoints, positions, fitted, layout, times, *, bleaching, blinking, psf
) -> dict:
    """One calibration's part of ``validation.json``, with its warnings: blinking, the
    trend within acquisitions (corrected or not), the beads' means, the frames whose fits
    converged, the PSF checks and repeated set-points."""
    conv = fitted.conv[ci]
    I = np.where(conv, fitted.arr["intensity"][ci], np.nan)  # (B, S, F)
    I_se = np.where(conv, fitted.arr_se["intensity"][ci], np.nan)
    blink = blinking_level(I, I_se)
    off = blink["off"]
    n_off = off.sum(axis=2)  # (B, S)
    if n_off.any():
        warnings.warn(
            f"{cal.label}: {int(blink['detected'].any(axis=1).sum())} bead(s) switch off in "
            "some frames (blinking: "
            + ", ".join(f"{int(n)} frame(s) at {k}x" for k, n in zip(keys, n_off.sum(axis=0)) if n)
            + "); "
            + (
                "their mean intensities are the 'on' level of a two-level mixture"
                if blinking == "model"
                else "ignored (--blinking ignore): the off frames lower their means"
            ),
            stacklevel=4,
            category=BeadWarning,
        )
    trend = intensity_trend(np.where(off, np.nan, I), np.where(off, np.nan, I_se), times)
    trend["corrected"] = bool(trend["detected"] and bleaching == "correct")
    if trend["detected"]:
        warnings.warn(
            f"{cal.label}: the beads' intensity "
            f"{'falls' if trend['rate_per_frame'] > 0 else 'rises'} within the acquisitions "
            f"({100 * trend['fade_over_series']:+.2f} % over the series, {trend['z']:.1f} "
            "standard errors: bleaching or a drifting illumination); "
            + (
                "corrected before the set-points are compared"
                if trend["corrected"]
                else "not corrected (--bleaching warn): it adds to the differences between "
                "set-points"
            ),
            stacklevel=4,
            category=BeadWarning,
        )
    if trend["corrected"]:
        I = I * np.exp(trend["rate_per_frame"] * times)[None]
    beads = _bead_entries(I, blink, blinking, keys, setpoints, positions, fitted, ci)
    psf_doc = _psf_document(cal, fitted.mismatch[ci], layout, psf)

    def avg(name):
        v = np.array([b[name] for b in beads], dtype=float)
        v = v[np.isfinite(v)]
        return finite_or_none(v.mean()) if v.size else None

    return {
        "file": cal.label,
        "method": cal.method,
        "converged_fraction": _converged_fraction(cal, fitted, ci, keys),
        "psf": psf,
        "psf_mismatch": psf_doc,
        "blinking": {
            "frames_off": {k: int(v) for k, v in zip(keys, n_off.sum(axis=0))},
            "beads": int(blink["detected"].any(axis=1).sum()),
            "modelled": blinking == "model",
        },
        "repeats": _repeats(cal, layout, keys, I, off),
        "intensity_trend": {
            k: (finite_or_none(v) if isinstance(v, float) else v) for k, v in trend.items()
        },
        "beads": beads,
        **{
            name: avg(name)
            for name in (
                "sigma_means_incl_1x",
                "sigma_means_excl_1x",
                "sigma_means_incl_1x_ddof1",
                "sigma_means_excl_1x_ddof1",
            )
        },
        "beads_used": int(
            np.sum(np.isfinite(np.array([b["sigma_means_incl_1x"] for b in beads], dtype=float)))
        ),
    }


def _bead_entries(I, blink, blinking, keys, setpoints, positions, fitted, ci) -> list:
    """Each bead's mean intensity at every set-point (the 'on' level where it blinks and
    that is modelled), its SE (the frames' scatter, and the two errors common to the
    frames: the offset map's and the bead's shared parameters') and the consistency
    metric."""
    off, n_off = blink["off"], blink["off"].sum(axis=2)
    on_level = _on_level(I, blink["off_probability"])
    use_on = blink["detected"] & (blinking == "model")
    conv, arr, offset_se = fitted.conv[ci], fitted.arr, fitted.offset_se[ci]
    shared_se = fitted.shared_se[ci]
    entries = []
    for b, (r, c) in enumerate(positions):
        vals = I[b]  # (S, F)
        with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.where(use_on[b], on_level[b], np.nanmean(vals, axis=1))
            kept = np.where(use_on[b][:, None] & off[b], np.nan, vals)
            n = np.sum(np.isfinite(kept), axis=1)
            scatter = np.nanstd(kept, axis=1, ddof=1) / np.sqrt(n)
            se = np.sqrt(scatter**2 + offset_se[b] ** 2 + shared_se[b] ** 2)
            y = np.nanmedian(np.where(conv[b], arr["y"][ci, b], np.nan))
            x = np.nanmedian(np.where(conv[b], arr["x"][ci, b], np.nan))
        metric = {d: consistency(dict(zip(setpoints, mean)), ddof=d) for d in (0, 1)}
        entries.append(
            {
                "row": int(r),
                "col": int(c),
                "mean_intensity": {k: finite_or_none(v) for k, v in zip(keys, mean)},
                "mean_intensity_se": {k: finite_or_none(v) for k, v in zip(keys, se)},
                "mean_intensity_se_offset": {
                    k: finite_or_none(v) for k, v in zip(keys, offset_se[b])
                },
                "mean_intensity_se_shared": {
                    k: finite_or_none(v) for k, v in zip(keys, shared_se[b])
                },
                "sigma_means_incl_1x": finite_or_none(metric[0][0]),
                "sigma_means_excl_1x": finite_or_none(metric[0][1]),
                "sigma_means_incl_1x_ddof1": finite_or_none(metric[1][0]),
                "sigma_means_excl_1x_ddof1": finite_or_none(metric[1][1]),
                "frames_used": {k: int(v) for k, v in zip(keys, n)},
                "frames_off": {k: int(v) for k, v in zip(keys, n_off[b])},
                "fitted_row": finite_or_none(y),
                "fitted_col": finite_or_none(x),
            }
        )
    return entries


def _converged_fraction(cal, fitted, ci, keys) -> dict:
    """Per set-point, the fraction of fitted frames whose fits converged; warned below
    :data:`MIN_CONVERGED`."""
    conv = fitted.conv[ci]
    exists = np.isfinite(fitted.arr["intensity"][ci]) | conv  # frames that were fitted
    fraction = {
        k: finite_or_none(conv[:, si][exists[:, si]].mean()) if exists[:, si].any() else None
        for si, k in enumerate(keys)
    }
    low = {k: v for k, v in fraction.items() if v is not None and v < MIN_CONVERGED}
    if low:
        warnings.warn(
            f"{cal.label}: bead fits converged in only "
            + ", ".join(f"{100 * v:.1f} % at {k}x" for k, v in low.items())
            + " of frames; the means are over the others, which can bias them if the "
            "failures depend on the frames' brightness",
            stacklevel=5,
            category=BeadWarning,
        )
    return fraction


def _poor_fits(per_acquisition) -> dict:
    """χ² per pixel above :data:`PSF_CHI2`, by set-point key."""
    return {
        k: m["chi2_per_pixel"]
        for k, m in per_acquisition.items()
        if m.get("chi2_per_pixel") is not None and m["chi2_per_pixel"] > PSF_CHI2
    }


def _psf_document(cal, mismatch, layout, psf) -> dict:
    """The PSF checks of each spot model per acquisition; a warning where the Gaussian
    does not describe the beads' mean images, and where the residual image does not
    describe the frames it was not built on."""
    doc = {
        model: {
            slot.key: {q: finite_or_none(v) for q, v in m.items()}
            for slot, m in zip(layout, per_acquisition)
        }
        for model, per_acquisition in mismatch.items()
    }
    poor = _poor_fits(doc["gaussian"])
    held_out = _poor_fits(doc.get(psf, {})) if psf != "gaussian" else {}
    if held_out:
        warnings.warn(
            f"{cal.label}: the residual image does not describe the frames it was not "
            "built on (held-out chi2 per pixel "
            + ", ".join(f"{v:.1f} at {k}x" for k, v in held_out.items())
            + "): the spot's shape differs between the halves of the frames, or from "
            "what the image could learn (--psf-split time tests a change over time)",
            stacklevel=5,
            category=BeadWarning,
        )
    if poor:
        warnings.warn(
            f"{cal.label}: the Gaussian spot does not describe the beads' mean images "
            "(chi2 per pixel "
            + ", ".join(f"{v:.1f} at {k}x" for k, v in poor.items())
            + "): the PSF is not Gaussian, or this calibration's pixel-to-pixel error in "
            "e_per_adu or gain puts the same pattern in every frame (then other "
            "calibrations of the same beads score lower); "
            + (
                "the residual image was added (--psf " + psf + ")"
                if psf != "gaussian"
                else "a PSF mismatch can weigh differently at different set-points: "
                "try --psf residual"
            ),
            stacklevel=5,
            category=BeadWarning,
        )
    return doc


def _repeats(cal, layout, keys, I, off):
    """A set-point recorded more than once: each later acquisition's beads against the
    first's, after the trend correction (``I`` (B, S, F) as corrected, off frames left
    out). Mean over beads of the ratio of their means, its SE (SD over beads / √B) and z;
    warned beyond :data:`TREND_Z`: something changed over the series that the frames'
    own time course does not show (light lost between acquisitions, focus)."""
    out = []
    I = np.where(off, np.nan, I)
    for si, key in enumerate(keys):
        slots = [slot for slot in layout if slot.row == si]
        if len(slots) < 2:
            continue
        with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            means = [
                np.nanmean(I[:, si, slot.first : slot.first + slot.acq.n_frames], axis=1)
                for slot in slots
            ]
            later = []
            for slot, m in zip(slots[1:], means[1:]):
                a = slot.acq
                r = m / means[0]
                r = r[np.isfinite(r)]
                se = float(np.std(r, ddof=1) / np.sqrt(r.size)) if r.size > 1 else math.nan
                ratio = float(np.mean(r)) if r.size else math.nan
                z = (ratio - 1) / se if se > 0 else math.nan
                later.append(
                    {
                        "acquisition": a.name,
                        "key": slot.key,
                        "ratio": finite_or_none(ratio),
                        "ratio_se": finite_or_none(se),
                        "z": finite_or_none(z),
                        "beads": int(r.size),
                    }
                )
                if abs(z) > TREND_Z:
                    warnings.warn(
                        f"{cal.label}: the beads' mean intensity at {key}x changed by "
                        f"{100 * (ratio - 1):+.2f} % between acquisitions "
                        f"'{slots[0].acq.name}' and '{a.name}' ({z:.1f} standard errors), "
                        "beyond the trend within the acquisitions: light lost between "
                        "them, or a change of focus or illumination",
                        stacklevel=5,
                        category=BeadWarning,
                    )
        out.append({"setpoint": key, "first": slots[0].acq.name, "later": later})
    return out


def _intensities_dataset(cals, setpoints, positions, fitted, manifest, layout):
    import xarray as xr

    arr, arr_se, loglik, conv = fitted.arr, fitted.arr_se, fitted.loglik, fitted.conv

    from .. import __version__

    dims = ("calibration", "bead", "setpoint", "frame")
    units = {"x": "pixel", "y": "pixel", "width": "pixel", "intensity": "e-", "background": "e-"}
    long = {
        "x": "fitted bead centre, column (sensor pixel coordinates)",
        "y": "fitted bead centre, row (sensor pixel coordinates)",
        "width": "fitted PSF standard deviation",
        "intensity": "fitted bead intensity: photoelectrons per frame (whole bead)",
        "background": "fitted background: photoelectrons per pixel per frame",
    }
    data = {}
    for n in ("intensity", "x", "y", "width", "background"):
        data[n] = (dims, arr[n], {"units": units[n], "long_name": long[n]})
        data[n + "_se"] = (
            dims,
            arr_se[n],
            {"units": units[n], "long_name": "standard error of " + long[n]},
        )
    data["loglik"] = (
        dims,
        loglik,
        {"units": "nat", "long_name": "maximised log-likelihood of the bead's box"},
    )
    data["converged"] = (dims, conv, {"units": "1", "long_name": "fit converged (usable)"})
    coords = {
        "calibration": (
            "calibration",
            [c.label for c in cals],
            {"long_name": "calibration file(s) the beads were fitted under"},
        ),
        "method": ("calibration", [c.method for c in cals], {"long_name": "calibration method"}),
        "bead": ("bead", np.arange(len(positions)), {"long_name": "bead index"}),
        "bead_row": (
            "bead",
            positions[:, 0].astype(int),
            {"units": "pixel", "long_name": "row of the bead's box centre"},
        ),
        "bead_col": (
            "bead",
            positions[:, 1].astype(int),
            {"units": "pixel", "long_name": "column of the bead's box centre"},
        ),
        "setpoint": (
            "setpoint",
            np.array(setpoints, dtype=float),
            {"units": "1", "long_name": "EM gain set-point of the camera"},
        ),
        "frame": (
            "frame",
            np.arange(arr["intensity"].shape[-1]),
            {
                "long_name": "frame index within the set-point (a repeated set-point's "
                "acquisitions one after another)"
            },
        ),
        "acquisition": (
            ("setpoint", "frame"),
            _acquisition_names(layout, arr),
            {"long_name": "the acquisition (manifest name) of each frame"},
        ),
    }
    return xr.Dataset(
        data,
        coords=coords,
        attrs={
            "emccdcal_version": __version__,
            "bead_manifest": str(manifest.path),
            "bead_manifest_sha256": manifest.content_hash,
            "note": "NaN and converged = 0 where a frame does not exist at a set-point or a bead "
            "was left out for a calibration",
        },
    )


def _acquisition_names(layout, arr):
    names = np.full(arr["intensity"].shape[-2:], "", dtype=object)
    for slot in layout:
        names[slot.row, slot.first : slot.first + slot.acq.n_frames] = slot.acq.name
    return names.astype(str)


def read_validation(directory):
    """Read a bead-validation directory: ``validation.json`` and, if there, ``intensities.nc``.

    Parameters
    ----------
    directory : str or Path
        The ``-o`` directory of ``emccdcal validate``.

    Returns
    -------
    doc : dict
        ``validation.json``: ``calibrations`` (each with ``file``, ``method``, ``beads``
        and the consistency metrics) and ``ranking``; set-points are string keys.
    intensities : xarray.DataArray or None
        ``intensity`` (e⁻) with dims (calibration, bead, setpoint, frame), or None when
        ``intensities.nc`` is absent.

    Raises
    ------
    FileNotFoundError
        No ``validation.json`` in ``directory``.
    ValueError
        A file that is not a validation file of this contract (names the file).
    """

    d = Path(directory)
    path = d / VALIDATION_FILE
    if not path.is_file():
        raise MissingFileError(f"{path}: no such file (not a validation directory?)")
    try:
        doc = _files.load_json(path, what="bead-validation file")
        cals = doc["calibrations"]
        if not isinstance(cals, list) or not all("beads" in c for c in cals):
            raise TypeError("'calibrations' must be a list of objects with 'beads'")
    except (ValueError, KeyError, TypeError) as exc:
        raise OptionError(
            f"{path}: not a bead-validation file ({exc.__class__.__name__}: {exc})"
        ) from None
    ipath = d / INTENSITIES_FILE
    if not ipath.is_file():
        return doc, None
    f = read_netcdf(ipath, what="validation")
    try:
        da = f["intensity"]
        if "converged" in f:  # frames whose fit did not converge are not shown
            da = da.where(f["converged"].astype(bool))
    except (ValueError, KeyError, TypeError) as exc:
        raise OptionError(
            f"{ipath}: not a readable intensities file ({exc.__class__.__name__}: {exc})"
        ) from None
    want = ("calibration", "bead", "setpoint", "frame")
    if set(da.dims) != set(want):
        raise OptionError(f"{ipath}: 'intensity' has dims {da.dims}; expected {want}")
    return doc, da.transpose(*want)


def data_checks(entry) -> list[str]:
    """What a calibration's validation found about the bead data, as short phrases:
    bleaching, blinking, a repeated set-point, a PSF the Gaussian does not describe.

    Parameters
    ----------
    entry : dict
        One item of ``validation.json``'s ``calibrations``.
    """
    out = []
    trend = entry.get("intensity_trend") or {}
    if trend.get("detected"):
        out.append(
            f"intensity trend {-100 * trend['fade_over_series']:+.2f} % over the series "
            f"(z {trend['z']:.1f}, {'corrected' if trend.get('corrected') else 'not corrected'})"
        )
    blink = entry.get("blinking") or {}
    off = sum((blink.get("frames_off") or {}).values())
    if off:
        out.append(
            f"{blink['beads']} bead(s) blinking, {off} frame(s) off "
            f"({'on level taken' if blink.get('modelled') else 'ignored'})"
        )
    for rep in entry.get("repeats") or []:
        for later in rep["later"]:
            if later["ratio"] is not None:
                out.append(
                    f"{rep['setpoint']}x recorded again: {later['ratio']:.4f} ± "
                    f"{later['ratio_se'] or float('nan'):.4f} of the first"
                )
    gauss = (entry.get("psf_mismatch") or {}).get("gaussian") or {}
    chi2 = [m["chi2_per_pixel"] for m in gauss.values() if m.get("chi2_per_pixel") is not None]
    if chi2 and max(chi2) > PSF_CHI2:
        out.append(
            f"Gaussian misfits the mean images (chi2/pixel up to {max(chi2):.1f}: "
            "PSF, or the calibration's pixel-to-pixel error; "
            + (
                "residual image added)"
                if entry.get("psf", "gaussian") != "gaussian"
                else "Gaussian kept)"
            )
        )
    model = entry.get("psf", "gaussian")
    held_out = (
        _poor_fits((entry.get("psf_mismatch") or {}).get(model) or {})
        if model != "gaussian"
        else {}
    )
    if held_out:
        out.append(
            f"residual image misfits held-out frames (chi2/pixel up to "
            f"{max(held_out.values()):.1f})"
        )
    return out


def format_table(doc) -> str:
    """The ranking as a short text table (σ of means in % of the 1× mean, ddof = 0)."""
    by_file = {c["file"]: c for c in doc["calibrations"]}
    n_beads = max((len(c["beads"]) for c in doc["calibrations"]), default=0)
    head = (
        f"bead validation: {n_beads} beads, set-points {', '.join(doc['setpoints'])} "
        "(sigma of per-set-point means / 1x mean, ddof 0, mean over beads)"
    )
    lines = [head, f"  {'rank':>4}  {'method':<22} {'incl 1x':>8} {'excl 1x':>8}  file"]

    def pct(v):
        return "     n/a" if v is None else f"{100 * v:7.3f}%"

    for i, f in enumerate(doc["ranking"], start=1):
        c = by_file[f]
        lines.append(
            f"  {i:>4}  {c['method']:<22} {pct(c['sigma_means_incl_1x'])} "
            f"{pct(c['sigma_means_excl_1x'])}  {f}"
        )
        lines += [f"{'':8}{check}" for check in data_checks(c)]
    return "\n".join(lines)
