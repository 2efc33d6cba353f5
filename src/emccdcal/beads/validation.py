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
differ between set-points; the second pass gives the intensities. ``converged_fraction``
says per set-point how many frames converged, and below 99 % a warning says so.

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
import json
import math
import time
import warnings
from pathlib import Path

import numpy as np

from .. import result
from .._util import atomic_write, atomic_write_text, finite_or_none
from .._util import progress as progress_bar
from ..data.manifest import Manifest, read_manifest
from ..errors import InputError, MissingFileError, OptionError
from . import fit as bead_fit

__all__ = [
    "VALIDATION_FILE",
    "INTENSITIES_FILE",
    "DDOF",
    "consistency",
    "intensity_trend",
    "validate",
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
    by = {}
    for a in manifest.acquisitions:
        s = float(a.em_gain_setpoint)
        if s in by:
            raise InputError(
                f"{manifest.path}: acquisitions '{by[s].name}' and '{a.name}' are both at "
                f"set-point {result.format_setpoint(s)}x; a bead manifest has one per set-point"
            )
        by[s] = a
    if 1.0 not in by:
        raise InputError(
            f"{manifest.path}: no acquisition at set-point 1; the consistency metric is "
            "scaled to each bead's 1x mean intensity"
        )
    return dict(sorted(by.items()))


def _frame_times(manifest, setpoints, F):
    """Each frame's place in the recorded series (frames since the first), shape (S, F):
    the acquisitions in the manifest's order, as they were recorded."""
    start, t0 = {}, 0
    for a in manifest.acquisitions:
        start[float(a.em_gain_setpoint)] = t0
        t0 += a.n_frames
    return np.array([start[s] for s in setpoints], float)[:, None] + np.arange(F)[None, :]


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
        return {"rate_per_frame": None, "rate_se": None, "z": None, "fade_over_series": None,
                "detected": False}
    k = -float((w * x * yc).sum()) / sxx
    chi2 = float((w * (yc + k * x) ** 2).sum())
    dof = int((w > 0).sum()) - int(use.sum()) - 1
    rate_se = math.sqrt(max(1.0, chi2 / dof) / sxx) if dof > 0 else math.sqrt(1 / sxx)
    span = float(np.nanmax(times) - np.nanmin(times))
    z = k / rate_se
    return {"rate_per_frame": k, "rate_se": rate_se, "z": z,
            "fade_over_series": -math.expm1(-k * span), "detected": bool(abs(z) > z_detect)}


def _detect(manifest, acqs, setpoint, width, half_size, min_separation, snr):
    s = max(acqs) if setpoint is None else float(setpoint)
    if s not in acqs:
        raise OptionError(f"{manifest.path}: no acquisition at set-point "
                         f"{result.format_setpoint(s)}x to detect the beads on")
    acq = acqs[s]
    found = bead_fit.detect_beads(acq.frames(), acq.offset, width=width, half_size=half_size,
                                min_separation=min_separation, snr=snr)
    where = f"{acq.frames_path} (mean image, threshold {found.threshold:.4g} ADU above background)"
    if len(found.at_edge):
        warnings.warn(
            f"{acq.frames_path}: skipped {len(found.at_edge)} bead(s) closer than {half_size} px "
            f"to the frame's edge at (row, col) {_pairs(found.at_edge)}",
            stacklevel=3,
        )
    if len(found.too_close):
        warnings.warn(
            f"{acq.frames_path}: skipped {len(found.too_close)} bead(s) with another bead "
            f"inside their fitting box at (row, col) {_pairs(found.too_close)}",
            stacklevel=3,
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


def validate(bead_manifest, calibrations, *, out=None, width=bead_fit.DEFAULT_WIDTH,
             half_size=bead_fit.DEFAULT_HALF_SIZE, min_separation=None, snr=8.0,
             detect_setpoint=None, progress=False, bleaching="correct") -> dict:
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
        A progress bar on stderr.
    bleaching : {"correct", "warn"}
        What to do where the beads' intensity trends within the acquisitions
        (:func:`intensity_trend`: bleaching, or a drifting illumination): undo it (each
        frame's intensity times e^(k t), t its place in the series, the acquisitions in
        the manifest's order) before the means are compared, or only warn. Either way
        ``validation.json`` reports it (``intensity_trend``).

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
    """
    t0 = time.perf_counter()
    if bleaching not in TREND_ACTIONS:
        raise OptionError(f"bleaching must be one of {', '.join(TREND_ACTIONS)}; got "
                          f"{bleaching!r}")
    manifest = bead_manifest if isinstance(bead_manifest, Manifest) \
        else read_manifest(bead_manifest)
    if not calibrations:
        raise OptionError("give at least one calibration to validate")
    acqs = _acquisitions_by_setpoint(manifest)
    setpoints = list(acqs)
    cals = [result.load_calibration(c, manifest.shape, of="the bead frames")
            for c in calibrations]
    for cal in cals:
        for s in setpoints:
            cal.gain(s)  # raises for a missing set-point, before any fitting
    found, det_acq = _detect(manifest, acqs, detect_setpoint, width, half_size,
                             min_separation, snr)
    positions = found.positions
    B, S = len(positions), len(setpoints)
    Fmax = max(a.n_frames for a in acqs.values())
    names = ("x", "y", "width", "intensity", "background")
    shape = (len(cals), B, S, Fmax)
    arr = {n: np.full(shape, np.nan) for n in names}
    arr_se = {n: np.full(shape, np.nan) for n in names}
    loglik = np.full(shape, np.nan)
    conv = np.zeros(shape, bool)
    cache: dict = {}

    def fit_at(cal, s, ok, fixed=None):
        """The beads ``ok`` at set-point ``s`` under ``cal`` (cached: calibrations that
        agree there share the fit)."""
        acq, g = acqs[s], cal.gain(s)
        key = (s, positions[ok].tobytes(), _boxes_bytes(cal.e_per_adu, positions[ok],
                                                       half_size),
               _boxes_bytes(g, positions[ok], half_size), cal.em_model,
               None if fixed is None else fixed.tobytes())
        if key not in cache:
            cache[key] = bead_fit.fit_beads(
                acq.frames(), positions[ok], offset=acq.offset, read_noise=acq.read_noise,
                e_per_adu=cal.e_per_adu, em_gain=g, half_size=half_size, width=width,
                adc_max=manifest.adc_max, em_model=cal.em_model, fixed_width=fixed)
        return cache[key]

    with progress_bar(enabled=progress, desc="fitting beads", unit="stack",
                      total=2 * len(cals) * S) as bar:
        for ci, cal in enumerate(cals):
            ok = np.ones(B, bool)
            for s in setpoints:
                bad = ~_box_ok(cal.e_per_adu, cal.gain(s), positions, half_size)
                if bad.any():
                    warnings.warn(
                        f"{cal.label}: no usable e_per_adu (> 0) or gain (>= 1) at "
                        f"{result.format_setpoint(s)}x in the box of {int(bad.sum())} bead(s) "
                        f"at (row, col) {_pairs(positions[bad])}; left out for this calibration",
                        stacklevel=2,
                    )
                ok &= ~bad
            # Pass 1: each set-point with the width free (shared by its frames); the
            # widths pooled over set-points are every bead's one width for pass 2.
            first = []
            for s in setpoints:
                bar.set_postfix_str(f"{cal.method} {result.format_setpoint(s)}x (width)")
                first.append(fit_at(cal, s, ok))
                bar.update(1)
            widths = bead_fit.shared_widths(first)
            for si, s in enumerate(setpoints):
                bar.set_postfix_str(f"{cal.method} {result.format_setpoint(s)}x")
                acq = acqs[s]
                fit = fit_at(cal, s, ok, widths) if np.isfinite(widths).all() else first[si]
                F = acq.n_frames
                idx = np.flatnonzero(ok)
                for j, n in enumerate(names):
                    arr[n][ci, idx, si, :F] = fit.params[..., j]
                    arr_se[n][ci, idx, si, :F] = fit.se[..., j]
                loglik[ci, idx, si, :F] = fit.loglik
                conv[ci, idx, si, :F] = fit.converged
                if fit.n_saturated and ci == 0:
                    warnings.warn(f"{acq.frames_path}: {fit.n_saturated} count(s) at the ADC "
                                  "maximum in the bead boxes were left out of the fits",
                                  stacklevel=2)
                bar.update(1)

    times = _frame_times(manifest, setpoints, Fmax)
    doc = _summarise(manifest, cals, setpoints, positions, arr, arr_se, conv, times, bleaching,
                     det_acq, half_size,
                     time.perf_counter() - t0)
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        ds = _intensities_dataset(cals, setpoints, positions, arr, arr_se, loglik, conv,
                                  manifest)
        atomic_write(out / INTENSITIES_FILE, lambda p: ds.to_netcdf(p, engine="h5netcdf"))
        text = json.dumps(doc, indent=2, allow_nan=False) + "\n"
        atomic_write_text(out / VALIDATION_FILE, text)
    return doc


def _boxes_bytes(m, positions, half_size):
    return b"".join(
        np.ascontiguousarray(m[r - half_size:r + half_size + 1, c - half_size:c + half_size + 1])
        .tobytes() for r, c in positions)


def _summarise(manifest, cals, setpoints, positions, arr, arr_se, conv, times, bleaching,
               det_acq, half_size, seconds):
    keys = [result.format_setpoint(s) for s in setpoints]
    I = np.where(conv, arr["intensity"], np.nan)
    entries = []
    for ci, cal in enumerate(cals):
        trend = intensity_trend(I[ci], np.where(conv[ci], arr_se["intensity"][ci], np.nan),
                                times)
        trend["corrected"] = bool(trend["detected"] and bleaching == "correct")
        if trend["detected"]:
            warnings.warn(
                f"{cal.label}: the beads' intensity {'falls' if trend['rate_per_frame'] > 0 else 'rises'} "
                f"within the acquisitions ({100 * trend['fade_over_series']:+.2f} % over the "
                f"series, {trend['z']:.1f} standard errors: bleaching or a drifting "
                "illumination); "
                + ("corrected before the set-points are compared" if trend["corrected"] else
                   "not corrected (--bleaching warn): it adds to the differences between "
                   "set-points"), stacklevel=3)
        if trend["corrected"]:
            I[ci] = I[ci] * np.exp(trend["rate_per_frame"] * times)[None]
        bead_entries = []
        per = {d: {"incl": [], "excl": []} for d in (0, 1)}
        for b, (r, c) in enumerate(positions):
            vals = I[ci, b]  # (S, F)
            n = np.sum(np.isfinite(vals), axis=1)
            with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                mean = np.nanmean(vals, axis=1)
                se = np.nanstd(vals, axis=1, ddof=1) / np.sqrt(n)
                y = np.nanmedian(np.where(conv[ci, b], arr["y"][ci, b], np.nan))
                x = np.nanmedian(np.where(conv[ci, b], arr["x"][ci, b], np.nan))
            means = dict(zip(setpoints, mean))
            metric = {d: consistency(means, ddof=d) for d in (0, 1)}
            for d in (0, 1):
                per[d]["incl"].append(metric[d][0])
                per[d]["excl"].append(metric[d][1])
            bead_entries.append({
                "row": int(r),
                "col": int(c),
                "mean_intensity": {k: finite_or_none(v) for k, v in zip(keys, mean)},
                "mean_intensity_se": {k: finite_or_none(v) for k, v in zip(keys, se)},
                "sigma_means_incl_1x": finite_or_none(metric[0][0]),
                "sigma_means_excl_1x": finite_or_none(metric[0][1]),
                "sigma_means_incl_1x_ddof1": finite_or_none(metric[1][0]),
                "sigma_means_excl_1x_ddof1": finite_or_none(metric[1][1]),
                "frames_used": {k: int(v) for k, v in zip(keys, n)},
                "fitted_row": finite_or_none(y),
                "fitted_col": finite_or_none(x),
            })

        def avg(values):
            v = np.array(values, dtype=float)
            v = v[np.isfinite(v)]
            return finite_or_none(v.mean()) if v.size else None

        exists = np.isfinite(arr["intensity"][ci]) | conv[ci]  # frames that were fitted
        fraction = {k: finite_or_none(conv[ci][:, si][exists[:, si]].mean())
                    if exists[:, si].any() else None for si, k in enumerate(keys)}
        low = {k: v for k, v in fraction.items() if v is not None and v < MIN_CONVERGED}
        if low:
            warnings.warn(
                f"{cal.label}: bead fits converged in only "
                + ", ".join(f"{100 * v:.1f} % at {k}x" for k, v in low.items())
                + " of frames; the means are over the others, which can bias them if the "
                "failures depend on the frames' brightness", stacklevel=3)
        entries.append({
            "file": cal.label,
            "method": cal.method,
            "converged_fraction": fraction,
            "intensity_trend": {k: (finite_or_none(v) if isinstance(v, float) else v)
                                for k, v in trend.items()},
            "beads": bead_entries,
            "sigma_means_incl_1x": avg(per[0]["incl"]),
            "sigma_means_excl_1x": avg(per[0]["excl"]),
            "sigma_means_incl_1x_ddof1": avg(per[1]["incl"]),
            "sigma_means_excl_1x_ddof1": avg(per[1]["excl"]),
            "beads_used": int(np.sum(np.isfinite(per[0]["incl"]))),
        })
    order = sorted(range(len(entries)), key=lambda i: (
        entries[i]["sigma_means_incl_1x"] is None,
        entries[i]["sigma_means_incl_1x"] if entries[i]["sigma_means_incl_1x"] is not None else 0.0))
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
        "units": {"mean_intensity": "e- per frame (whole bead)", "mean_intensity_se": "e-",
                  "sigma_means": "1 (fraction of the 1x mean)", "row": "pixel", "col": "pixel"},
        "bead_manifest": str(manifest.path),
        "bead_manifest_sha256": manifest.content_hash,
        "detected_on": str(det_acq.frames_path),
        "half_size": int(half_size),
        "emccdcal_version": __version__,
        "created": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "seconds": finite_or_none(seconds),
    }


def _intensities_dataset(cals, setpoints, positions, arr, arr_se, loglik, conv, manifest):
    import xarray as xr

    from .. import __version__

    dims = ("calibration", "bead", "setpoint", "frame")
    units = {"x": "pixel", "y": "pixel", "width": "pixel", "intensity": "e-",
             "background": "e-"}
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
        data[n + "_se"] = (dims, arr_se[n], {"units": units[n],
                                             "long_name": "standard error of " + long[n]})
    data["loglik"] = (dims, loglik, {"units": "nat",
                                     "long_name": "maximised log-likelihood of the bead's box"})
    data["converged"] = (dims, conv, {"units": "1", "long_name": "fit converged (usable)"})
    coords = {
        "calibration": ("calibration", [c.label for c in cals],
                        {"long_name": "calibration file(s) the beads were fitted under"}),
        "method": ("calibration", [c.method for c in cals], {"long_name": "calibration method"}),
        "bead": ("bead", np.arange(len(positions)), {"long_name": "bead index"}),
        "bead_row": ("bead", positions[:, 0].astype(int),
                     {"units": "pixel", "long_name": "row of the bead's box centre"}),
        "bead_col": ("bead", positions[:, 1].astype(int),
                     {"units": "pixel", "long_name": "column of the bead's box centre"}),
        "setpoint": ("setpoint", np.array(setpoints, dtype=float),
                     {"units": "1", "long_name": "EM gain set-point of the camera"}),
        "frame": ("frame", np.arange(arr["intensity"].shape[-1]),
                  {"long_name": "frame index within the acquisition"}),
    }
    return xr.Dataset(data, coords=coords, attrs={
        "emccdcal_version": __version__,
        "bead_manifest": str(manifest.path),
        "bead_manifest_sha256": manifest.content_hash,
        "note": "NaN and converged = 0 where a frame does not exist at a set-point or a bead "
                "was left out for a calibration",
    })


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
    import xarray as xr

    d = Path(directory)
    path = d / VALIDATION_FILE
    if not path.is_file():
        raise MissingFileError(f"{path}: no such file (not a validation directory?)")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        cals = doc["calibrations"]
        if not isinstance(cals, list) or not all("beads" in c for c in cals):
            raise TypeError("'calibrations' must be a list of objects with 'beads'")
    except (ValueError, KeyError, TypeError) as exc:
        raise OptionError(f"{path}: not a bead-validation file ({exc.__class__.__name__}: "
                         f"{exc})") from None
    ipath = d / INTENSITIES_FILE
    if not ipath.is_file():
        return doc, None
    try:
        with xr.open_dataset(ipath, engine="h5netcdf") as f:
            da = f["intensity"].load()
            if "converged" in f:  # frames whose fit did not converge are not shown
                da = da.where(f["converged"].load().astype(bool))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise OptionError(f"{ipath}: not a readable intensities file ({exc.__class__.__name__}: "
                         f"{exc})") from None
    want = ("calibration", "bead", "setpoint", "frame")
    if set(da.dims) != set(want):
        raise OptionError(f"{ipath}: 'intensity' has dims {da.dims}; expected {want}")
    return doc, da.transpose(*want)



def format_table(doc) -> str:
    """The ranking as a short text table (σ of means in % of the 1× mean, ddof = 0)."""
    by_file = {c["file"]: c for c in doc["calibrations"]}
    n_beads = max((len(c["beads"]) for c in doc["calibrations"]), default=0)
    head = (f"bead validation: {n_beads} beads, set-points {', '.join(doc['setpoints'])} "
            "(sigma of per-set-point means / 1x mean, ddof 0, mean over beads)")
    lines = [head, f"  {'rank':>4}  {'method':<22} {'incl 1x':>8} {'excl 1x':>8}  file"]

    def pct(v):
        return "     n/a" if v is None else f"{100 * v:7.3f}%"

    for i, f in enumerate(doc["ranking"], start=1):
        c = by_file[f]
        lines.append(f"  {i:>4}  {c['method']:<22} {pct(c['sigma_means_incl_1x'])} "
                     f"{pct(c['sigma_means_excl_1x'])}  {f}")
    return "\n".join(lines)
