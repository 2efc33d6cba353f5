"""Running a validation: the beads detected on the series, fitted under each calibration (:func:`fit_validation`, :class:`BeadFits`), and :func:`validate`, which writes the result document."""

from __future__ import annotations

import functools
import json
import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ... import identity, result
from ..._output import atomic_write, atomic_write_text, write_netcdf
from ..._util import progress as progress_bar
from ...data.manifest import Manifest, read_manifest
from ...errors import BeadWarning, InputError, OptionError
from .. import fit as bead_fit
from .. import psf_check
from .metric import (
    BLINK_ACTIONS,
    INTENSITIES_FILE,
    PSF_MODELS,
    TREND_ACTIONS,
    VALIDATION_FILE,
    _acquisitions_by_setpoint,
    _frame_layout,
)
from .document import _intensities_dataset, _summarise


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
    each spot model (:func:`emccdcal.beads.psf_check.psf_mismatch`) per acquisition.
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
        (:func:`emccdcal.beads.psf_check.residual_image`; "residual-pooled": one image for all
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
    widths, widths_se = psf_check.shared_widths(first, with_se=True)
    if not np.isfinite(widths).all():
        widths = None
    fits = []
    for j, slot in enumerate(layout):
        bar.set_postfix_str(f"{method} {slot.key}x")
        fits.append(fit_at(j, ok, widths, fixed_se=widths_se) if widths is not None else first[j])
        bar.update(1)
    gaussian = [psf_check.psf_mismatch(f) for f in fits]
    if psf != "gaussian":  # the paper's second pass: the residual image added,
        # built on half 0 of the frames; half 1 scores it (psf_mismatch below)
        image = psf_check.residual_image(fits, per_bead=psf == "residual", half=0)
        fits = []
        for j, slot in enumerate(layout):
            bar.set_postfix_str(f"{method} {slot.key}x (residual)")
            fits.append(fit_at(j, ok, widths, image, fixed_se=widths_se))
            bar.update(1)
    return fits, {"gaussian": gaussian} | (
        {}
        if psf == "gaussian"
        else {psf: [psf_check.psf_mismatch(f, half=1, image=image) for f in fits]}
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
