"""Per-stack checks, streamed over the frames: a stack's summary (:class:`StackSummary`), frame means, saturation, hot and dead pixels, and one acquisition's checks (:func:`check_acquisition`)."""

from __future__ import annotations

import math

import numpy as np

from ...errors import (
    InputError,
)
from ..dark import as_stack, maps_from_dark
from .drift import (
    DEFAULT_ALPHA,
    DEFAULT_DRIFT_THRESHOLD,
    DEFAULT_K,
    DRIFT_ALPHA,
    MIN_FRAMES,
    _MIN_PIXELS_DEFECTS,
    _pixels,
    drift_test,
    robust_spread,
    stationarity,
)


#: Elements (frames × pixels) converted to float64 at a time when streaming a stack.
_CHUNK_ELEMENTS = 2**23


# --------------------------------------------------------------------------------------
# Per-stack checks
# --------------------------------------------------------------------------------------
def _chunks(stack: np.ndarray):
    n_frames = stack.shape[0]
    per_frame = max(1, int(np.prod(stack.shape[1:])))
    step = max(1, _CHUNK_ELEMENTS // per_frame)
    for f0 in range(0, n_frames, step):
        yield f0, np.asarray(stack[f0 : f0 + step])


class StackSummary:
    """What the data-quality checks need of one stack, accumulated part by part.

    A calibration reads each stack once, tile by tile; it adds every tile's
    :func:`band_statistics` here (:meth:`add`), and the checks then need no second read.
    Per frame: the sum of the counts over the pixels seen and whether any was saturated;
    per pixel: the mean and SD over all frames (:func:`emccdcal.data.dark.maps_from_dark`)
    and the number of saturated frames (counts at or above ``adc_max``).

    Parameters
    ----------
    n_frames : int
        Frames of the stack.
    shape : tuple of int
        (rows, cols).
    adc_max : int or None
        ADC maximum, ADU; None: saturation is not counted.
    """

    def __init__(self, n_frames: int, shape, adc_max: int | None):
        if adc_max is not None and (
            isinstance(adc_max, bool) or int(adc_max) != adc_max or adc_max < 1
        ):
            raise InputError(f"adc_max must be a positive integer, got {adc_max!r}")
        self.adc_max = None if adc_max is None else int(adc_max)
        self.n_frames = int(n_frames)
        self.shape = tuple(int(d) for d in shape)
        n_pixels = self.shape[0] * self.shape[1]
        self.frame_sums = np.zeros(self.n_frames)
        self.frame_min = np.full(self.n_frames, np.inf)
        self.frame_max = np.full(self.n_frames, -np.inf)
        self.frame_keys = np.zeros(self.n_frames, dtype=np.uint64)
        self.frame_saturated = np.zeros(self.n_frames, dtype=bool)
        self.mean = np.full(n_pixels, np.nan)  # per pixel, C order
        self.sd = np.full(n_pixels, np.nan)
        self.n_saturated = np.zeros(n_pixels, dtype=np.int64)
        self.m3 = np.full(n_pixels, np.nan)  # third central moments, where computed
        self.seen = np.zeros(n_pixels, dtype=bool)

    @classmethod
    def of(cls, stack, adc_max: int | None, *, third: bool = False) -> StackSummary:
        """The summary of a whole stack, read in bands of rows of bounded size (``third``:
        with the pixels' third moments)."""
        stack = as_stack(stack)
        out = cls(stack.shape[0], stack.shape[1:], adc_max)
        per_row = max(1, int(stack.shape[0]) * int(stack.shape[2]))
        step = max(1, _CHUNK_ELEMENTS // per_row)
        for r0 in range(0, stack.shape[1], step):
            out.add(
                r0 * stack.shape[2],
                band_statistics(np.asarray(stack[:, r0 : r0 + step]), adc_max, third=third),
            )
        return out

    @classmethod
    def of_file(
        cls, path, skip_frames: int, adc_max: int | None, *, third: bool = False
    ) -> StackSummary:
        """The summary of a stack file from ``skip_frames`` on, read band by band of rows
        into memory (:func:`emccdcal.data.stacks.read_band`): bounded memory, and no
        mapped pages counted against the process, whatever the stack's size."""
        from ..stacks import read_band, stack_header

        (n, rows, cols), _ = stack_header(path)
        out = cls(n - skip_frames, (rows, cols), adc_max)
        step = max(1, _CHUNK_ELEMENTS // max(1, (n - skip_frames) * cols))
        for r0 in range(0, rows, step):
            band = read_band(path, r0, r0 + step, skip_frames)
            out.add(r0 * cols, band_statistics(band, adc_max, third=third))
        return out

    def add(self, first: int, statistics: dict) -> None:
        """Add the :func:`band_statistics` of the pixels from ``first`` on (C order)."""
        n = statistics["mean"].size
        part = slice(first, first + n)
        if self.seen[part].any():
            raise ValueError(f"pixels {first}..{first + n - 1} were already added")
        self.frame_sums += statistics["frame_sums"]
        if "frame_min" in statistics:
            np.minimum(self.frame_min, statistics["frame_min"], out=self.frame_min)
            np.maximum(self.frame_max, statistics["frame_max"], out=self.frame_max)
            # the part's place makes a frame's key depend on where its values are
            mix = np.uint64(2 * first + 1)
            with np.errstate(over="ignore"):
                self.frame_keys += statistics["frame_keys"].astype(np.uint64) * mix
        self.frame_saturated |= statistics["frame_saturated"]
        self.mean[part] = statistics["mean"].ravel()
        self.sd[part] = statistics["sd"].ravel()
        self.n_saturated[part] = statistics["n_saturated"].ravel()
        if "m3" in statistics:
            self.m3[part] = statistics["m3"].ravel()
        self.seen[part] = True

    def _complete(self):
        if not self.seen.all():
            raise ValueError(
                f"pixels {np.flatnonzero(~self.seen)[:5].tolist()}... were never added"
            )

    def frame_means(self, offset=None) -> np.ndarray:
        """Per-frame mean of the (offset-subtracted) counts over all pixels, ADU
        (as :func:`frame_means`)."""
        self._complete()
        off = 0.0 if offset is None else float(np.mean(np.asarray(offset, dtype=np.float64)))
        return self.frame_sums / (self.shape[0] * self.shape[1]) - off

    def saturation(self) -> dict:
        """As :func:`saturation`."""
        self._complete()
        n_values = int(self.n_saturated.sum())
        return {
            "adc_max": self.adc_max,
            "n_values": n_values,
            "fraction": n_values / max(1, self.n_frames * self.n_saturated.size),
            "n_frames": int(np.count_nonzero(self.frame_saturated)),
            "n_pixels": int(np.count_nonzero(self.n_saturated)),
            "pixels": _pixels(self.n_saturated.reshape(self.shape) > 0),
        }

    def frame_defects(self) -> dict:
        """Frames a camera or its software got wrong: ``constant`` (every pixel the same
        value, e.g. all zero: a dropped frame) and ``repeated`` (a frame identical to an
        earlier one: a frame written twice), each with their indices (first 10) and count."""
        self._complete()
        constant = np.flatnonzero(self.frame_min == self.frame_max)
        _, first = np.unique(self.frame_keys, return_index=True)
        repeated = np.setdiff1d(np.arange(self.n_frames), first)
        repeated = repeated[~np.isin(repeated, constant)]  # said once, as constant
        return {
            "n_constant": int(constant.size),
            "constant": constant[:10].tolist(),
            "n_repeated": int(repeated.size),
            "repeated": repeated[:10].tolist(),
        }

    def offset_position(self, offset) -> dict:
        """Where the offset map lies against the pixels' mean counts: ``n_pixels``,
        ``n_below_offset`` (pixels whose mean count is below their offset) and
        ``above_data`` (more than half of them: the offset cannot be this data's)."""
        self._complete()
        below = self.mean < np.broadcast_to(np.asarray(offset, float), self.shape).ravel()
        return {
            "n_pixels": int(below.size),
            "n_below_offset": int(below.sum()),
            "above_data": bool(2 * below.sum() > below.size),
        }

    def multiplication_ratio(self, offset, read_noise) -> dict | None:
        """Whether counts taken as 1× look EM-multiplied, from their first three cumulants.

        With κ₁ = mean − offset, κ₂ = variance − σ² and κ₃ the third central moment
        (Gaussian read noise adds nothing to it), R = κ₃κ₁/κ₂² is 1 for Poisson
        photoelectrons times any φ, and 1.5 once an EM register multiplies them
        (gamma model: κ₃ = 6Eg³, κ₂ = 2Eg², κ₁ = Eg, in electrons), whatever E, g and φ.
        Returns ``R`` (mean over pixels), ``R_se``, ``n_pixels`` and ``multiplied``
        (R closer to 1.5 than to 1 and above 1 by more than four standard errors), or
        None when the third moments were not gathered or fewer than 3 pixels qualify.
        """
        self._complete()
        k1 = self.mean - np.broadcast_to(np.asarray(offset, float), self.shape).ravel()
        k2 = self.sd**2 - np.broadcast_to(np.asarray(read_noise, float), self.shape).ravel() ** 2
        good = np.isfinite(self.m3) & (k1 > 0) & (k2 > 0)
        if good.sum() < 3:
            return None
        ratio = self.m3[good] * k1[good] / k2[good] ** 2
        r, se = float(ratio.mean()), float(ratio.std(ddof=1) / math.sqrt(ratio.size))
        return {
            "R": r,
            "R_se": se,
            "n_pixels": int(ratio.size),
            "multiplied": bool(r > 1.25 and r - 1 > 4 * se),
        }

    def defects(self, offset=None, *, k: float = DEFAULT_K, telegraph=None) -> dict:
        """As :func:`pixel_defects`; ``telegraph`` (rows, cols) of bool, the pixels whose
        dark holds two or more offset states: those hot or dead are listed apart
        (``n_telegraph``/``telegraph``), their offset is not one number."""
        self._complete()
        return _defects(
            self.mean.reshape(self.shape),
            self.sd.reshape(self.shape),
            self.n_frames,
            offset,
            k,
            telegraph,
        )


def _frame_keys(flat: np.ndarray) -> np.ndarray:
    """A 64-bit fingerprint of each frame's part (frames, pixels): equal frames give
    equal keys, different ones almost surely not. A stack's key per frame is the sum of
    its parts' keys (:meth:`StackSummary.add`), whatever the order they come in."""
    import zlib

    rows = np.ascontiguousarray(flat)
    crc = [
        zlib.crc32(rows[i].tobytes()) ^ (zlib.adler32(rows[i].tobytes()) << 32)
        for i in range(rows.shape[0])
    ]
    return np.array(crc, dtype=np.uint64)


def band_statistics(band: np.ndarray, adc_max: int | None, *, third: bool = False) -> dict:
    """What a :class:`StackSummary` needs of a band of rows held in memory.

    Parameters
    ----------
    band : ndarray, shape (frames, h, cols)
        Raw counts, ADU.
    adc_max : int or None
        ADC maximum, ADU.

    third : bool, optional
        Also ``m3`` (h, cols), the third central moment of each pixel's counts (ADU³),
        for :meth:`StackSummary.multiplication_ratio`.

    Returns
    -------
    dict of ndarray
        ``frame_sums`` (frames,), ``frame_saturated`` (frames,), ``mean``, ``sd`` and
        ``n_saturated`` (h, cols): small enough to keep for every band of a full sensor.
    """
    n = band.shape[0]
    mean, sd = maps_from_dark(band) if n >= 2 else (band[0].astype(float), np.zeros(band.shape[1:]))
    if adc_max is None:
        sat_frames: np.ndarray = np.zeros(n, dtype=bool)
        sat_pixels = np.zeros(band.shape[1:], dtype=np.int64)
    else:
        sat = band >= adc_max
        sat_frames = np.asarray(sat.reshape(n, -1).any(axis=1))
        sat_pixels = sat.sum(axis=0, dtype=np.int64)
    flat = band.reshape(n, -1)
    out = {
        "frame_sums": flat.sum(axis=1, dtype=np.float64),
        "frame_min": flat.min(axis=1).astype(np.float64),
        "frame_max": flat.max(axis=1).astype(np.float64),
        "frame_keys": _frame_keys(flat),
        "frame_saturated": sat_frames,
        "mean": mean,
        "sd": sd,
        "n_saturated": sat_pixels,
    }
    if third:  # of 1× data, for multiplication_ratio
        m3 = np.zeros(band.shape[1:])
        step = max(1, _CHUNK_ELEMENTS // max(1, mean.size))  # frames converted at a time
        for f0 in range(0, n, step):
            dev = np.asarray(band[f0 : f0 + step], float) - mean
            m3 += np.einsum("fij,fij,fij->ij", dev, dev, dev)
        out["m3"] = m3 / n
    return out


def _defects(mean, sd, n_frames, offset, k, telegraph=None) -> dict:
    """Hot, dead and stuck pixels from per-pixel means and SDs (:func:`pixel_defects`),
    random-telegraph pixels (``telegraph``) among the hot and dead listed apart."""
    if not (math.isfinite(k) and k > 0):
        raise InputError(f"k must be a positive number, got {k!r}")
    mean = np.asarray(mean, dtype=np.float64)
    sd = np.asarray(sd, dtype=np.float64)
    if offset is not None:
        mean = mean - np.asarray(offset, dtype=np.float64)
    stuck = sd == 0
    out = {
        "k": float(k),
        "tested": False,
        "median_mean": float(np.median(mean)),
        "robust_sd": None,
        "n_hot": 0,
        "hot": [],
        "n_dead": 0,
        "dead": [],
        "n_stuck": int(np.count_nonzero(stuck)),
        "stuck": _pixels(stuck),
        "n_telegraph": 0,
        "telegraph": [],
    }
    if mean.size < _MIN_PIXELS_DEFECTS:
        return out
    med, scale = robust_spread(mean, float(np.median(sd)) / math.sqrt(n_frames))
    out.update(tested=True, robust_sd=scale)
    if scale > 0:
        z = (mean - med) / scale
        moved = np.zeros(z.shape, dtype=bool) if telegraph is None else np.asarray(telegraph)
        hot, dead = (z > k) & ~moved, (z < -k) & ~moved
        moved = moved & (np.abs(z) > k)
        out.update(
            n_hot=int(np.count_nonzero(hot)),
            hot=_pixels(hot),
            n_dead=int(np.count_nonzero(dead)),
            dead=_pixels(dead),
            n_telegraph=int(np.count_nonzero(moved)),
            telegraph=_pixels(moved),
        )
    return out


def frame_means(stack, offset=None) -> np.ndarray:
    """Per-frame mean over all pixels of the (offset-subtracted) counts.

    Parameters
    ----------
    stack : array_like, shape (frames, rows, cols)
        Raw counts, ADU (a memory map is read in chunks).
    offset : float or array_like (rows, cols), optional
        Offset map S0 (ADU) subtracted from every frame; default 0.

    Returns
    -------
    ndarray of float64, shape (frames,)
        ADU.
    """
    stack = as_stack(stack)
    off = 0.0 if offset is None else float(np.mean(np.asarray(offset, dtype=np.float64)))
    out = np.empty(stack.shape[0])
    for f0, chunk in _chunks(stack):
        out[f0 : f0 + chunk.shape[0]] = chunk.reshape(chunk.shape[0], -1).mean(
            axis=1, dtype=np.float64
        )
    return out - off


def saturation(stack, adc_max: int) -> dict:
    """Count saturated values: counts at or above the ADC maximum.

    Parameters
    ----------
    stack : array_like, shape (frames, rows, cols)
        Raw counts, ADU.
    adc_max : int
        ADC maximum, ADU (``2**bits − 1``).

    Returns
    -------
    dict
        ``adc_max``; ``n_values`` (saturated pixel-frames), ``fraction`` (of all
        pixel-frames); ``n_frames`` (frames with at least one saturated pixel);
        ``n_pixels`` (pixels saturated in at least one frame) and ``pixels`` (their
        [row, col], at most :data:`MAX_LISTED`).

    Examples
    --------
    >>> s = saturation(np.array([[[1, 7]], [[7, 2]], [[3, 4]]]), adc_max=7)
    >>> s["n_values"], s["n_frames"], s["n_pixels"]
    (2, 2, 2)
    """
    stack = as_stack(stack)
    return StackSummary.of(stack, adc_max).saturation()


def pixel_defects(stack, offset=None, *, k: float = DEFAULT_K) -> dict:
    """Hot, dead and stuck pixels of a stack, by robust statistics of the pixel means.

    A pixel is *hot* when its mean count exceeds the median of all pixel means by more
    than ``k`` robust standard deviations, *dead* when it falls short by as much, and
    *stuck* when its counts never change (variance 0). The robust standard deviation is
    1.4826 × the median absolute deviation of the pixel means, floored at the median
    standard error of a pixel mean (so that a perfectly uniform sensor flags nothing by
    round-off).

    Parameters
    ----------
    stack : array_like, shape (frames, rows, cols)
        Raw counts, ADU (≥ 2 frames; a memory map is read in chunks).
    offset : float or array_like (rows, cols), optional
        Offset map S0 (ADU) subtracted from the pixel means, so that a fixed offset
        pattern does not count as a defect; default 0.
    k : float, optional
        Threshold in robust standard deviations (default 5).

    Returns
    -------
    dict
        ``k``; ``median_mean`` (ADU), ``robust_sd`` (ADU, None when there are too few
        pixels); ``n_hot``/``hot``, ``n_dead``/``dead``, ``n_stuck``/``stuck`` (counts and
        [row, col] lists, at most :data:`MAX_LISTED`); ``n_telegraph``/``telegraph``
        (random-telegraph pixels as hot or dead, where a calibration's darks found them;
        here none); ``tested`` (False when fewer than 5 pixels: only stuck pixels are then
        looked for).
    """
    stack = as_stack(stack)
    if int(stack.shape[0]) < 2:
        raise InputError(f"pixel_defects needs at least 2 frames, got {int(stack.shape[0])}")
    return StackSummary.of(stack, None).defects(offset, k=k)


def check_acquisition(
    acq,
    adc_max: int,
    *,
    k: float = DEFAULT_K,
    drift_threshold: float = DEFAULT_DRIFT_THRESHOLD,
    drift_alpha: float = DRIFT_ALPHA,
    unit_root_tests: bool = False,
    alpha: float = DEFAULT_ALPHA,
    regression: str = "c",
    summary: StackSummary | None = None,
) -> dict:
    """All data-quality checks of one acquisition.

    Parameters
    ----------
    acq : emccdcal.data.manifest.Acquisition
        The acquisition (its frames after ``skip_frames`` and its offset map are used).
    adc_max : int
        ADC maximum, ADU (``Manifest.adc_max``).
    k : float, optional
        As in :func:`pixel_defects`.
    drift_threshold, drift_alpha : float, optional
        ``threshold`` and ``alpha`` of :func:`drift_test` (this acquisition's own level).
    unit_root_tests : bool, optional
        Also run ADF and KPSS (:func:`stationarity`, with ``alpha`` and ``regression``);
        reported, never a finding. Default False.
    summary : StackSummary, optional
        The acquisition's statistics, accumulated while something else read the stack (a
        calibration does); default: read the stack now.

    Returns
    -------
    dict
        ``name``, ``frames`` (path), ``em_gain_setpoint``, ``level`` (label or None),
        ``n_frames``, ``shape``; ``drift`` (:func:`drift_test` of the per-frame mean of
        the offset-subtracted counts, None with fewer than :data:`MIN_FRAMES` frames);
        ``stationarity`` (:func:`stationarity`, or None); ``saturation``
        (:func:`saturation`); ``pixels`` (:func:`pixel_defects` on the
        offset-subtracted pixel means); ``offset``
        (:meth:`StackSummary.offset_position`); ``multiplication`` (at set-point 1:
        :meth:`StackSummary.multiplication_ratio`, else None).

    Raises
    ------
    InputError
        Naming the frames file, when its frame means cannot be tested (not finite).
    """
    path = acq.frames_path
    n = int(acq.n_frames)
    one_x = float(acq.em_gain_setpoint) == 1
    if summary is None:
        summary = StackSummary.of_file(acq.frames_path, acq.skip_frames, adc_max, third=one_x)
    series = summary.frame_means(acq.offset)
    drift = stat = None
    if n >= MIN_FRAMES:
        try:
            drift = drift_test(series, alpha=drift_alpha, threshold=drift_threshold)
            if unit_root_tests:
                stat = stationarity(series, regression=regression, alpha=alpha)
        except ValueError as exc:
            raise InputError(f"'{path}': frame means: {exc}") from None
    return {
        "name": acq.name,
        "frames": str(path),
        "em_gain_setpoint": float(acq.em_gain_setpoint),
        "level": acq.level,
        "skip_frames": int(acq.skip_frames),
        "n_frames": n,
        "shape": [int(d) for d in acq.shape],
        "drift": drift,
        "photoelectrons_estimate": _moment_photoelectrons(summary, acq, one_x),
        "stationarity": stat,
        "saturation": summary.saturation(),
        "frames_defective": summary.frame_defects(),
        "pixels": summary.defects(acq.offset, k=k, telegraph=acq.dark_telegraph),
        "offset": summary.offset_position(acq.offset),
        "multiplication": summary.multiplication_ratio(acq.offset, acq.read_noise)
        if one_x
        else None,
    }


def _moment_photoelectrons(summary, acq, one_x: bool) -> float | None:
    """E (e⁻ per pixel per frame) from the counts' moments alone, median over pixels:
    F²·(mean − S0)²/(var − σ²), F² = 1 at 1× and 2 multiplied (no φ or g needed); for
    saying what a finding does at this acquisition's own level. None where undefined."""
    signal = summary.mean - np.ravel(acq.offset)
    excess = summary.sd**2 - np.ravel(acq.read_noise) ** 2
    ok = (signal > 0) & (excess > 0)
    if not ok.any():
        return None
    return float(np.median((1.0 if one_x else 2.0) * signal[ok] ** 2 / excess[ok]))
