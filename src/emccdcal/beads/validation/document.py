"""The validation's result document: each calibration's entry (its metric, beads, repeats, spot model), the intensities' dataset, reading a validation back (:func:`read_validation`), the checks of its data (:func:`data_checks`) and its table (:func:`format_table`)."""

from __future__ import annotations

import datetime as _dt
import math
import warnings
from pathlib import Path

import numpy as np

from ... import _files, result
from ..._output import read_netcdf
from ..._util import finite_or_none
from ...errors import BeadWarning, MissingFileError, OptionError
from .metric import (
    DDOF,
    INTENSITIES_FILE,
    MIN_CONVERGED,
    PSF_CHI2,
    TREND_Z,
    VALIDATION_FILE,
    _frame_times,
    _on_level,
    blinking_level,
    consistency,
    intensity_trend,
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
    from ... import __version__

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

    from ... import __version__

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
