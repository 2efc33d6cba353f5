"""``emccdcal apply``: a movie's raw counts to photoelectrons per pixel, streaming.

Each frame ``S`` (ADU) becomes ``E = (S − S0) · φ / g`` (e⁻), with the offset ``S0``, φ
and the gain ``g`` of each pixel at the movie's EM-gain set-point. The movie is read a
block of frames at a time (about 64 MB) and written as it is read, so memory stays
bounded whatever the movie's size; the output is written to a temporary name and renamed
when complete, so an interrupted run leaves no half-written file.

Photon counting (``photon_counting=True``, for high gain): a pixel counts 1 in a frame
where ``S − S0 > τ``, else 0, with the threshold ``τ = threshold · σ`` in read-noise SDs
(default 5: a false count in 2.9e-7 of pixel-frames from read noise alone). One
photoelectron clears it with probability ``exp(−τ φ / g)`` (the gamma model's tail of one
electron's output, ``g/φ`` ADU on average): that efficiency is recorded in the output's
metadata and a warning is given below 0.9. The counts are not corrected for it, nor for
two electrons in one pixel-frame (coincidence loss, negligible below ~0.1 e⁻ per
pixel-frame). References: Basden, Haniff & Mackay, MNRAS 345, 985 (2003); Lantz et al.,
MNRAS 386, 2262 (2008).
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import defaults, identity
from .._output import Output, atomic_write
from .._util import install_hint
from .._util import progress as progress_bar
from ..data.stacks import read_band, stack_header, stack_settings
from ..errors import ExportWarning, InputError, OptionError, spelled
from ..result import Calibration, format_setpoint, load_calibration

__all__ = ["apply", "conversion", "Conversion", "OUTPUT_FORMATS", "DEFAULT_THRESHOLD"]

OUTPUT_FORMATS = ("tiff", "zarr")
#: Photon-counting threshold in read-noise SDs.
DEFAULT_THRESHOLD = defaults.PHOTON_THRESHOLD
_BLOCK_BYTES = 16 << 20


def _movie_setpoint(movie: Path, recorded, given, no_register=False) -> float:
    """The movie's set-point: given, recorded, or 1 for a camera without an EM register
    (``no_register``: the calibration's ``camera_kind`` says so)."""
    if given is None and recorded is None and no_register:
        return 1.0
    if given is None and recorded is None:
        raise OptionError(
            f"{movie}: the file records no EM gain set-point and its name states "
            f"none (such as '300x'); give {spelled('--setpoint G')}"
        )
    if given is not None and recorded is not None and float(given) != recorded:
        raise OptionError(
            f"{movie}: set-point {format_setpoint(given)} given, but the file "
            f"records {format_setpoint(recorded)}"
        )
    return float(recorded if given is None else given)


def _region(cal: Calibration, movie: Path, roi, shape) -> tuple[slice, slice]:
    """The calibration's rows and columns that the movie's pixels are: placed by the
    movie's recorded ROI and the calibration's sensor origin where both are known, else
    the two must be the same size."""
    rows, cols = shape
    R, C = cal.shape
    if roi is None or cal.origin is None:
        if (rows, cols) != (R, C):
            unknown = (
                "the movie records no region"
                if roi is None
                else "the calibration does not know its place on the sensor"
            )
            raise InputError(
                f"{movie}: its {rows}×{cols} frames are not the calibration's {R}×{C} pixels "
                f"({cal.label}), and {unknown} to place them by"
            )
        return slice(0, R), slice(0, C)
    r0, c0 = roi[1] - cal.origin[0], roi[0] - cal.origin[1]
    if r0 < 0 or c0 < 0 or r0 + rows > R or c0 + cols > C:
        raise InputError(
            f"{movie}: its {rows}×{cols} frames at sensor row {roi[1]}, column "
            f"{roi[0]} are not inside the calibration's {R}×{C} pixels at row "
            f"{cal.origin[0]}, column {cal.origin[1]} ({cal.label})"
        )
    return slice(r0, r0 + rows), slice(c0, c0 + cols)


def apply(
    calibration,
    movie,
    out,
    *,
    setpoint=None,
    photon_counting=False,
    threshold=DEFAULT_THRESHOLD,
    output_format=None,
    progress=True,
    overwrite=False,
    accept_mismatch=(),
    qe=None,
) -> Path:
    """Convert a movie to photoelectrons (or photons, or photon counts) per pixel per
    frame.

    Parameters
    ----------
    calibration : xarray.Dataset, Calibration, str or Path
        A calibration, or result file(s) for :func:`~emccdcal.result.load_calibration`.
    movie : str or Path
        Any stack emccdcal reads (TIFF, SPE, SIF, FITS, Zarr, .npy), raw counts in ADU.
    out : str or Path
        The output: ``.tif``/``.tiff`` (BigTIFF, float32 e⁻ or uint8 counts) or ``.zarr``
        (a directory store; needs the ``zarr`` extra).
    setpoint : float, optional
        The movie's EM-gain set-point; by default the one its file records (an error
        where it records none). Given and recorded must agree.
    photon_counting : bool
        Threshold each pixel-frame into 0/1 instead (see the module's notes).
    threshold : float
        The photon-counting threshold in read-noise SDs (default 5).
    output_format : {"tiff", "zarr"}, optional
        Default: from the suffix of ``out``.
    overwrite : bool
        Replace an existing ``out`` (only once the new one is complete; a ``.zarr`` only
        where emccdcal wrote it). Never allowed: ``out`` being the movie or a result.
    accept_mismatch : iterable of str
        Identity fields (:data:`~emccdcal.result.IDENTITY_FIELDS`) in which the movie
        may differ from the calibration.
    qe : float, optional
        The camera's quantum efficiency at the emission wavelength (photoelectrons per
        photon, 0 < QE ≤ 1): the output is then photons, photoelectrons / QE. Not with
        ``photon_counting``.
    progress : bool
        A progress bar over the frames (default): in a notebook or on a terminal; none in
        a pipe.

    Returns
    -------
    Path
        ``out``.

    Raises
    ------
    OptionError, InputError
        No set-point known, one missing from the calibration, a movie that is not inside
        the calibration's pixels or of another camera or read-out state, an output that
        exists (without ``overwrite``) or is an input, an output format not known, no
        pixel with a usable calibration.

    Examples
    --------
    >>> import tempfile, emccdcal
    >>> work = tempfile.mkdtemp()
    >>> sim = emccdcal.simulate_gain_series(
    ...     f"{work}/gs", rows=4, cols=4, frames=400, setpoints=(1, 10), seed=1, progress=False
    ... )
    >>> ds = emccdcal.calibrate(sim.manifest, e_per_adu=sim.truth["e_per_adu"], progress=False)
    >>> out = emccdcal.apply_calibration(
    ...     ds, sim.outdir / "gain-GS" / "10x-gain.tif", f"{work}/e.tif", setpoint=10,
    ...     progress=False,
    ... )
    >>> import tifffile
    >>> tifffile.imread(out).shape  # photoelectrons per pixel and frame
    (400, 4, 4)
    """
    movie, out = Path(movie), Path(out)
    fmt = output_format or (
        "zarr"
        if out.suffix.lower() == ".zarr"
        else "tiff"
        if out.suffix.lower() in (".tif", ".tiff")
        else None
    )
    if fmt not in OUTPUT_FORMATS:
        raise OptionError(
            f"{out}: write .tif/.tiff or .zarr (or give the format: {', '.join(OUTPUT_FORMATS)})"
        )
    if photon_counting and not (threshold > 0 and math.isfinite(threshold)):
        raise OptionError(f"--threshold is in read-noise SDs and positive; got {threshold}")
    if qe is not None:
        if not (isinstance(qe, (int, float)) and 0 < qe <= 1):
            raise OptionError(
                f"--qe is the quantum efficiency, photoelectrons per photon "
                f"(0 < QE <= 1, e.g. 0.9 for 90 %); got {qe!r}"
            )
        if photon_counting:
            raise OptionError(
                "--qe gives photons from photoelectrons; photon counting gives "
                "0/1 events, which a QE does not scale: give one of them"
            )
    cal = load_calibration(calibration)
    target = Output(
        out,
        kind="store" if fmt == "zarr" else "file",
        inputs=[movie, *cal.files],
        overwrite=overwrite,
    )
    with target:
        _apply(
            cal,
            movie,
            target,
            setpoint,
            photon_counting,
            threshold,
            fmt,
            progress,
            accept_mismatch,
            qe,
        )
    return out


@dataclass
class Conversion:
    """What turns a movie's raw counts into photoelectrons (or photons, or photon
    counts), per pixel: ``(S − offset) · scale``, or ``S − offset > tau`` when photon
    counting; with the metadata recorded beside the output (:func:`conversion`)."""

    offset: np.ndarray  # ADU, float32, the movie's (rows, cols)
    scale: np.ndarray  # e- (or photons) per ADU, float32
    tau: np.ndarray | None  # ADU, float32: the photon-counting threshold
    meta: dict

    def __call__(self, raw):
        """The converted frames of ``raw`` (frames, rows, cols): float32 e⁻ (photons),
        or uint8 counts. Works on a NumPy array and, lazily, on a Dask array."""
        signal = raw.astype(np.float32) - self.offset
        if self.tau is not None:
            return (signal > self.tau).astype(np.uint8)
        return signal * self.scale


def conversion(
    cal,
    source,
    settings,
    shape,
    *,
    setpoint=None,
    photon_counting=False,
    threshold=DEFAULT_THRESHOLD,
    accept_mismatch=(),
    qe=None,
) -> Conversion:
    """The :class:`Conversion` of frames of ``shape`` (frames, rows, cols) from
    ``source`` (a file, or a name for the messages) whose file recorded ``settings``
    (:class:`~emccdcal.data.settings.CameraSettings`), by the calibration ``cal``; the
    checks and warnings of :func:`apply` (its parameters)."""
    frames, rows, cols = shape
    if frames == 0 or rows == 0 or cols == 0:
        raise InputError(f"{source}: holds no frames (shape {shape})")
    identity.check(
        cal.identity(), {source: settings}, label=cal.label, accept=accept_mismatch, what="frames"
    )
    no_register = cal.camera_kind in defaults.WITHOUT_EM_REGISTER
    s = _movie_setpoint(source, settings.em_gain_setpoint, setpoint, no_register)
    rr, cc = _region(cal, source, settings.roi, (rows, cols))
    scale = (cal.e_per_adu / cal.gain(s))[rr, cc]
    offset, sigma = (m[rr, cc] for m in cal.dark(s))
    bad = ~(np.isfinite(offset) & np.isfinite(scale))
    if bad.all():
        raise InputError(
            f"{source}: none of its {rows}×{cols} pixels has a converged "
            f"calibration at {format_setpoint(s)}x in {cal.label}; nothing to "
            "convert"
        )
    meta = {
        "units": "photoelectrons per pixel per frame (e-)"
        if not photon_counting
        else "photon counts per pixel per frame (0 or 1)",
        "source": str(source),
        "setpoint": s,
        "formula": "(S - offset) * e_per_adu / em_gain",
        "emccdcal": cal.provenance(),
        "uncalibrated_pixels": int(bad.sum()),
        "axes": "TYX",
    }
    if qe is not None:  # photons: photoelectrons / QE
        scale = scale / qe
        meta.update(
            units="photons per pixel per frame",
            formula="(S - offset) * e_per_adu / em_gain / qe",
            qe=float(qe),
        )
    if bad.any():
        warnings.warn(
            f"{source}: {int(bad.sum())} pixel(s) have no converged calibration at "
            f"{format_setpoint(s)}x; they are NaN (0 when photon counting)",
            stacklevel=3,
            category=ExportWarning,
        )
    tau = None
    if photon_counting:
        tau = (threshold * sigma).astype(np.float32)
        efficiency = float(np.nanmedian(np.exp(-threshold * sigma * scale)))
        meta.update(
            formula=f"1 if S - offset > {threshold:g} * read_noise else 0",
            threshold_read_noise_sd=threshold,
            single_electron_efficiency=efficiency,
        )
        if efficiency < 0.9:
            warnings.warn(
                f"{source}: at {format_setpoint(s)}x one photoelectron clears the "
                f"{threshold:g}-sigma threshold in only {efficiency:.0%} of cases "
                "(g/phi is too small against the read noise for photon counting), "
                "so the counts miss that many photons: record at a higher EM gain, "
                "or convert without --photon-counting",
                stacklevel=3,
                category=ExportWarning,
            )
    return Conversion(offset.astype(np.float32), scale.astype(np.float32), tau, meta)


def _apply(
    cal, movie, target, setpoint, photon_counting, threshold, fmt, progress, accept_mismatch, qe
):
    shape, dtype = stack_header(movie)
    if len(shape) != 3:
        raise InputError(f"{movie}: a movie is a stack of frames; this file holds shape {shape}")
    frames, rows, cols = shape
    convert = conversion(
        cal,
        movie,
        stack_settings(movie, setpoint_from_name=True),
        shape,
        setpoint=setpoint,
        photon_counting=photon_counting,
        threshold=threshold,
        accept_mismatch=accept_mismatch,
        qe=qe,
    )
    out_dtype = np.uint8 if photon_counting else np.float32
    meta = convert.meta
    per_block = max(1, _BLOCK_BYTES // (rows * cols * max(dtype.itemsize, 4)))

    def blocks(bar):
        for a in range(0, frames, per_block):
            raw = read_band(movie, 0, rows, skip_frames=a, stop_frame=min(frames, a + per_block))
            if raw.dtype.kind == "f":  # integer counts are valid by their type
                _check_counts(movie, raw, a)
            yield convert(raw)
            bar.update(raw.shape[0])

    with progress_bar(
        total=frames, enabled=progress, desc=f"apply {movie.name}", unit="frame"
    ) as bar:
        if fmt == "tiff":
            _write_tiff(target.path, blocks(bar), (frames, rows, cols), out_dtype, meta)
        else:
            _write_zarr(
                target.store(), blocks(bar), (frames, rows, cols), out_dtype, meta, per_block
            )


def _check_counts(movie: Path, raw: np.ndarray, first: int) -> None:
    """Counts stored as floats must still be counts: finite and not negative."""
    with np.errstate(invalid="ignore"):
        wrong = ~(np.isfinite(raw) & (raw >= 0))
    if wrong.any():
        i = first + int(np.flatnonzero(wrong.any(axis=(1, 2)))[0])
        raise InputError(
            f"{movie}: frame {i} holds counts that are negative or not finite; "
            "raw camera counts are neither"
        )


def _write_tiff(out: Path, blocks, shape, dtype, meta) -> None:
    import tifffile

    def frames():
        for block in blocks:
            yield from block.astype(dtype, copy=False)

    def write(tmp):
        # One grey-scale image per frame (never RGB, whatever the last axis), the axes
        # named, so that Fiji and napari open a time series.
        with tifffile.TiffWriter(tmp, bigtiff=True) as tw:
            tw.write(frames(), shape=shape, dtype=dtype, metadata=meta, photometric="minisblack")

    atomic_write(out, write)


def _write_zarr(store: Path, blocks, shape, dtype, meta, per_block) -> None:
    """Fill a new Zarr store (the Output puts it in place when complete)."""
    try:
        import zarr
    except ImportError:
        raise OptionError("writing .zarr needs zarr: " + install_hint("zarr")) from None
    z = zarr.open_array(
        str(store), mode="w", shape=shape, dtype=dtype, chunks=(per_block, shape[1], shape[2])
    )
    z.attrs.update(json.loads(json.dumps(meta)))
    at = 0
    for block in blocks:
        z[at : at + block.shape[0]] = block.astype(dtype, copy=False)
        at += block.shape[0]
