"""Per-pixel sufficient statistics of one acquisition.

The likelihood of a pixel's frames depends on its counts only through their histogram:
``log L = Σ_k counts[k] · log p(values[k])``. A pixel's 5000 frames typically take a
few hundred distinct values, so the fitting engine evaluates the noise model on those
values only, weighted by how often each occurs (docs/results.md, "Performance design").

:func:`histograms` computes these histograms for every pixel at once: the frames of a
block of pixels are sorted along the frame axis and run-length encoded row by row with
array operations; there is no Python loop over pixels. Pixels are processed in blocks so
that memory stays bounded for a full sensor.

Frames at or above the ADC maximum ``adc_max`` are saturated: their true value is
unknown, so they are left out of the histogram and of the mean and variance, and counted
in ``n_saturated``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import _xp
from ..errors import InputError

__all__ = ["PixelHistograms", "histograms", "frame_usage", "DEFAULT_CHUNK_ELEMENTS"]

#: Elements (pixels × frames) sorted at a time by :func:`histograms`: 2**23 elements,
#: i.e. at most 64 MiB per int64 work array.
DEFAULT_CHUNK_ELEMENTS = 2**23


@dataclass(eq=False)
class PixelHistograms:
    """Histograms of the counts of every pixel of one acquisition.

    Pixels are numbered in C order: pixel ``p`` is ``(p // cols, p % cols)``. Arrays
    with a ``K`` axis are padded at the end: the padding repeats the pixel's last
    (largest) value and has count 0, so they can be used directly in
    ``Σ counts · log p(values)``.

    Attributes
    ----------
    values : ndarray of int64, shape (P, K)
        Each pixel's distinct unsaturated count values (ADU), ascending, then padding.
        A pixel with no usable frame has values 0.
    counts : ndarray of float64, shape (P, K)
        Number of frames at each value (0 on the padding).
    n : ndarray of int64, shape (P,)
        Frames used (unsaturated), ``counts.sum(axis=1)``.
    n_saturated : ndarray of int64, shape (P,)
        Frames excluded because their count is at or above ``adc_max``.
    mean : ndarray of float64, shape (P,)
        Mean of the used counts, ADU (NaN where ``n == 0``).
    var : ndarray of float64, shape (P,)
        Variance of the used counts (ddof=1), ADU² (NaN where ``n < 2``).
    min, max : ndarray of int64, shape (P,)
        Smallest and largest used count, ADU (0 where ``n == 0``).
    shape : tuple of int
        (rows, cols) of the frames.
    adc_max : int or None
        The saturation threshold used, ADU (None: nothing was excluded).
    """

    values: np.ndarray
    counts: np.ndarray
    n: np.ndarray
    n_saturated: np.ndarray
    mean: np.ndarray
    var: np.ndarray
    min: np.ndarray
    max: np.ndarray
    shape: tuple[int, int]
    adc_max: int | None = None

    @property
    def n_pixels(self) -> int:
        """Number of pixels P."""
        return int(self.n.shape[0])

    @property
    def n_bins(self) -> int:
        """Width K of the ``values`` / ``counts`` arrays."""
        return int(self.values.shape[1])


def _as_count_block(block: np.ndarray) -> np.ndarray:
    """(F, Pc) frames of a block of pixels → (Pc, F) C-contiguous counts, native order.

    Integer data keep their (native byte order) integer type, so that sorting 16-bit data
    is a radix sort; float data must be integer-valued and are converted to int64.
    """
    kind = block.dtype.kind
    if kind in "ui":
        out = np.ascontiguousarray(block.T, dtype=block.dtype.newbyteorder("="))
    elif kind == "f":
        data = np.asarray(block, dtype=np.float64)
        if not np.all(np.isfinite(data)):
            raise InputError("frames contain NaN or infinite values; counts must be integers")
        if np.any(data != np.floor(data)):
            raise InputError("frames contain values that are not integers (raw ADU counts)")
        out = np.ascontiguousarray(data.T.astype(np.int64))
    else:
        raise InputError(f"frames must hold integer counts, got dtype {block.dtype}")
    return out


def _block_histograms(block: np.ndarray, adc_max: int | None):
    """Histograms of a (Pc, F) block of counts, in compact (run-list) form, NumPy arrays.

    The sort and the runs are computed where the fit computes (:func:`emccdcal._xp.engine`:
    the block goes there, its run lists come back). Runs are addressed by flat positions
    in the sorted block (row-major, so the runs of a row are consecutive): one 1-D
    gather, no 2-D fancy indexing.
    """
    xp, dev = _xp.engine()
    n_pix, n_frames = block.shape
    signed = block.dtype.kind == "i"
    # a stable sort of 8- and 16-bit counts is NumPy's radix sort
    s = xp.sort(_xp.on(xp, dev, block), axis=1, stable=block.dtype.itemsize <= 2)
    if n_frames and signed and bool(xp.any(s[:, 0] < 0)):
        raise InputError(
            "frames contain negative values; counts must be raw ADU (never offset-subtracted)"
        )
    if adc_max is None:
        n_used = xp.full(n_pix, n_frames, dtype=xp.int64, device=dev)
        starts = xp.ones(tuple(s.shape), dtype=xp.bool, device=dev)
    else:  # saturated values sort to the end of each row
        starts = s < adc_max
        n_used = xp.sum(xp.astype(starts, xp.int64), axis=1)
    # (a new array, not written in place: JAX's arrays are immutable)
    starts = xp.concat([starts[:, :1], starts[:, 1:] & (s[:, 1:] != s[:, :-1])], axis=1)
    run_pos = xp.nonzero(xp.reshape(starts, (-1,)))[0]
    run_row = run_pos // max(n_frames, 1)
    run_value = xp.astype(xp.take(xp.reshape(s, (-1,)), run_pos), xp.int64)
    # A run ends where the next one starts, or at the end of its row's usable values.
    last = xp.ones(1, dtype=xp.bool, device=dev)
    last_of_row = xp.concat([run_row[1:] != run_row[:-1], last])[: run_row.shape[0]]
    row_end = run_row * n_frames + xp.take(n_used, run_row)
    run_end = xp.where(last_of_row, row_end, xp.concat([run_pos[1:], run_pos[-1:]]))
    run_len = xp.astype(run_end - run_pos, xp.float64)
    n_runs = xp.astype(_xp.bincount(xp, run_row, None, n_pix), xp.int64)
    out = (run_row, run_value, run_len, n_runs, n_used, n_frames - n_used)
    return tuple(_xp.to_numpy(a) for a in out)


def histograms(frames, adc_max: int | None = None, *, chunk_pixels: int | None = None):
    """Per-pixel histograms of the counts of an acquisition.

    Parameters
    ----------
    frames : array_like, shape (F, rows, cols)
        Raw counts (ADU): integers, or integer-valued floats. A NumPy memmap is read one
        block of pixels at a time.
    adc_max : int, optional
        ADC maximum (ADU), ``2**bits - 1``. Counts at or above it are saturated: excluded
        from the histogram and the moments, counted in ``n_saturated``. None (default)
        excludes nothing.
    chunk_pixels : int, optional
        Pixels per block. Default: as many as keep a block within
        :data:`DEFAULT_CHUNK_ELEMENTS` elements. The result does not depend on it.

    Returns
    -------
    PixelHistograms
        With P = rows · cols pixels in C order.

    Raises
    ------
    ValueError
        If ``frames`` is not 3-D, or holds negative, NaN, infinite or non-integer values.

    Examples
    --------
    >>> frames = np.array([5, 7, 5, 9, 5]).reshape(5, 1, 1)
    >>> h = histograms(frames, adc_max=9)
    >>> h.values.tolist(), h.counts.tolist(), h.n.tolist(), h.n_saturated.tolist()
    ([[5, 7]], [[3.0, 1.0]], [4], [1])
    """
    if not hasattr(frames, "shape") or not hasattr(frames, "dtype"):
        frames = np.asarray(frames)
    elif not isinstance(frames, np.ndarray):  # a lazy store (Zarr) has no flat view: read it
        frames = np.asarray(frames[...])
    if frames.ndim != 3:
        raise InputError(
            f"frames must be 3-D (frames, rows, cols), got shape {tuple(frames.shape)}"
        )
    if adc_max is not None:
        if isinstance(adc_max, bool) or int(adc_max) != adc_max or adc_max < 1:
            raise InputError(f"adc_max must be a positive integer, got {adc_max!r}")
        adc_max = int(adc_max)
    n_frames, rows, cols = (int(d) for d in frames.shape)
    n_pix = rows * cols
    flat = frames.reshape(n_frames, n_pix)
    if chunk_pixels is None:
        chunk_pixels = max(1, DEFAULT_CHUNK_ELEMENTS // max(1, n_frames))
    elif int(chunk_pixels) < 1:
        raise InputError(f"chunk_pixels must be >= 1, got {chunk_pixels}")
    chunk_pixels = int(chunk_pixels)

    n = np.zeros(n_pix, dtype=np.int64)
    n_sat = np.zeros(n_pix, dtype=np.int64)
    n_runs = np.zeros(n_pix, dtype=np.int64)
    blocks = []
    for p0 in range(0, n_pix, chunk_pixels):
        p1 = min(n_pix, p0 + chunk_pixels)
        block = _as_count_block(flat[:, p0:p1])
        run_row, run_value, run_len, nr, n_used, n_s = _block_histograms(block, adc_max)
        n[p0:p1] = n_used
        n_sat[p0:p1] = n_s
        n_runs[p0:p1] = nr
        blocks.append((run_row + p0, run_value, run_len))

    run_row = np.concatenate([b[0] for b in blocks]) if blocks else np.zeros(0, np.int64)
    run_value = np.concatenate([b[1] for b in blocks]) if blocks else np.zeros(0, np.int64)
    run_len = np.concatenate([b[2] for b in blocks]) if blocks else np.zeros(0)

    # Scatter the runs into (P, K); the rank of a run within its pixel is its position
    # minus the position of the pixel's first run (runs are ordered by pixel).
    n_bins = max(1, int(n_runs.max(initial=0)))
    first_run = np.concatenate(([0], np.cumsum(n_runs)[:-1]))
    rank = np.arange(run_row.size) - first_run[run_row]
    cell = run_row * n_bins + rank
    counts = np.zeros((n_pix, n_bins), dtype=np.float64)
    counts.ravel()[cell] = run_len
    # Padding repeats the last value of each pixel (0 for a pixel without a usable frame).
    values = np.zeros((n_pix, n_bins), dtype=np.int64)
    values.ravel()[cell] = run_value
    last_value = np.take_along_axis(values, np.maximum(n_runs - 1, 0)[:, None], axis=1)
    values = np.where(np.arange(n_bins)[None, :] < n_runs[:, None], values, last_value)

    # The moments from the histogram: sums over its bins (padding counts 0).
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n > 0, np.sum(counts * values, axis=1) / n, np.nan)
        dev = values - mean[:, None]
        ss = np.sum(counts * dev * dev, axis=1)
        var = np.where(n > 1, ss / (n - 1), np.nan)
    has = n_runs > 0
    vmin = np.where(has, values[:, 0], 0)
    vmax = np.where(has, values[:, -1], 0)
    return PixelHistograms(
        values=values,
        counts=counts,
        n=n,
        n_saturated=n_sat,
        mean=mean,
        var=var,
        min=vmin,
        max=vmax,
        shape=(rows, cols),
        adc_max=adc_max,
    )


def frame_usage(frames, adc_max: int | None = None):
    """Which pixels have frames to fit, without building their histograms.

    Parameters
    ----------
    frames : ndarray, shape (F, rows, cols)
        Raw counts, ADU (checked counts: see :func:`emccdcal.data.stacks.check_counts`).
    adc_max : int, optional
        ADC maximum, ADU; counts at or above it are saturated (as in :func:`histograms`).

    Returns
    -------
    usable : ndarray of bool, shape (P,)
        Two or more unsaturated frames that are not all equal: what a fit needs
        (``n >= 2`` and ``max > min`` of :func:`histograms`).
    n_saturated : ndarray of int64, shape (P,)
        Saturated frames per pixel.

    Examples
    --------
    >>> frames = np.array([[5, 9], [5, 9], [7, 9]]).reshape(3, 1, 2)
    >>> usable, n_sat = frame_usage(frames, adc_max=9)
    >>> usable.tolist(), n_sat.tolist()
    ([True, False], [0, 3])
    """
    flat = np.asarray(frames).reshape(frames.shape[0], -1)
    if adc_max is None or flat.size == 0:
        n_sat = np.zeros(flat.shape[1], dtype=np.int64)
        sat = None
    else:
        sat = flat >= adc_max
        n_sat = sat.sum(axis=0, dtype=np.int64)
    if flat.shape[0] == 0:
        return np.zeros(flat.shape[1], dtype=bool), n_sat
    if sat is None or not n_sat.any():
        lo, hi = flat.min(axis=0), flat.max(axis=0)
    else:  # saturated counts are the largest: they change the maximum only
        lo = flat.min(axis=0)
        hi = np.where(sat, lo, flat).max(axis=0)
    return (flat.shape[0] - n_sat >= 2) & (hi > lo), n_sat
