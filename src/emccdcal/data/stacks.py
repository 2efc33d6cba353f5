"""Readers of stacks and maps: shape and dtype from the header, data memory-mapped.

Stacks are TIFF files (read with tifffile; memory-mapped when the file allows it, so a
large stack is not loaded until its frames are used) or ``.npy`` files (memory-mapped).
Counts, offsets and read noise are in ADU. Every problem is an
:class:`~emccdcal.errors.InputError` whose one-line message names the file.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np
import tifffile

from .._util import one_line
from ..errors import InputError, MissingFileError

__all__ = [
    "read_stack",
    "read_map",
    "load_stack",
    "read_band",
    "stack_header",
    "check_readable",
    "describe_missing",
    "describe_first",
    "check_counts",
    "needs_scan",
    "default_adc_max",
    "STACK_SUFFIXES",
]

#: File name suffixes of stacks and maps that can be read.
STACK_SUFFIXES = (".tif", ".tiff", ".npy")

#: Elements read at a time when scanning a stack's values.
_SCAN_ELEMENTS = 2**23


#: Bytes of whole frames :func:`read_band` reads per system call.
_READ_BYTES = 2**24


def read_band(path, first_row: int, stop_row: int, skip_frames: int = 0) -> np.ndarray:
    """Rows ``first_row:stop_row`` of every frame from ``skip_frames`` on, read into memory.

    Only those bytes are read (one ``preadv`` per frame, or per 16 MB of whole frames),
    so reading a band of a large
    stack neither loads the file nor maps it: a memory map would count the pages the
    kernel maps around every touched row (64 kB per frame) in the process's resident
    memory. Compressed or scattered TIFF data are read through tifffile instead.

    Returns
    -------
    ndarray, shape (frames - skip_frames, stop_row - first_row, cols)
        The file's dtype (possibly non-native byte order), raw counts.
    """
    path = check_readable(Path(path))
    layout = _raw_layout(path)
    if layout is None:
        return np.asarray(load_stack(path)[skip_frames:, first_row:stop_row])
    shape, dtype, offset = layout
    frames, rows, cols = shape
    first_row, stop_row = max(0, first_row), min(rows, stop_row)
    row_bytes = cols * dtype.itemsize
    frame_bytes = rows * row_bytes
    out = np.empty((max(0, frames - skip_frames), stop_row - first_row, cols), dtype=dtype)
    flat = out.reshape(out.shape[0], -1).view(np.uint8)
    want = flat.shape[1]
    # Whole frames lie back to back in the file: many per call. A band is scattered,
    # one call per frame.
    per_call = max(1, _READ_BYTES // frame_bytes) if want == frame_bytes else 1
    fd = os.open(path, os.O_RDONLY)
    try:
        for i in range(0, out.shape[0], per_call):
            part = flat[i:i + per_call]
            at = offset + (skip_frames + i) * frame_bytes + first_row * row_bytes
            got = os.preadv(fd, [part], at)
            if got != part.nbytes:
                raise InputError(f"'{path}': file ends inside frame "
                                 f"{skip_frames + i + got // want}: truncated")
    finally:
        os.close(fd)
    return out


def _raw_layout(path: Path):
    """(shape, dtype, data offset) of a 3-D stack stored as one C-ordered block, else None."""
    try:
        if path.suffix.lower() == ".npy":
            mm = np.load(path, mmap_mode="r", allow_pickle=False)  # reads the header only
            if mm.ndim != 3 or not mm.flags.c_contiguous:
                return None
            return tuple(mm.shape), mm.dtype, int(mm.offset)
        shape, dtype, offset = _tiff_layout(path)
        return None if offset is None or len(shape) != 3 else (shape, dtype, offset)
    except InputError:
        raise
    except (OSError, ValueError) as exc:
        raise InputError(f"'{path}': cannot read: {one_line(exc)}") from exc


def describe_missing(path: Path, what: str = "file") -> str:
    """``"<what> not found: '<path>' (resolved to '<absolute path>')"``."""
    return f"{what} not found: '{path}' (resolved to '{Path(path).expanduser().resolve()}')"


def check_readable(path: Path) -> Path:
    """``path`` if it is an existing file of a supported type, else an InputError."""
    path = Path(path)
    if not path.exists():
        raise MissingFileError(describe_missing(path))
    if path.is_dir():
        raise InputError(f"'{path}' is a directory, not a file")
    if path.suffix.lower() not in STACK_SUFFIXES:
        raise InputError(
            f"'{path}': unsupported file type '{path.suffix}' "
            f"(supported: {', '.join(STACK_SUFFIXES)})"
        )
    return path


def stack_header(path: Path) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of a stack or map from its header, without reading the data."""
    path = check_readable(path)
    try:
        if path.suffix.lower() == ".npy":
            arr = np.load(path, mmap_mode="r", allow_pickle=False)
            return tuple(arr.shape), arr.dtype
        shape, dtype, _ = _tiff_layout(path)
        return shape, dtype
    except InputError:
        raise
    except (OSError, ValueError) as exc:  # tifffile.TiffFileError is a ValueError
        raise InputError(f"'{path}': cannot read: {one_line(exc)}") from exc


def _tiff_layout(path: Path):
    """Shape, dtype (in the file's byte order) and offset of the data of a TIFF's one
    image series; the offset is None where the data are not one contiguous block.

    Finding them walks the file's page index (about 20 ms for 5000 frames), which a
    calibration would otherwise do several times per stack: it is done once per file
    version (path, size, modification time).
    """
    st = path.stat()
    return _tiff_layout_cached(str(path.resolve()), st.st_size, st.st_mtime_ns)


@functools.lru_cache(maxsize=128)
def _tiff_layout_cached(path: str, size: int, mtime_ns: int):
    with tifffile.TiffFile(path) as tif:
        if not tif.series:
            raise InputError(f"'{path}': TIFF file holds no image")
        if len(tif.series) > 1:  # reading only the first would drop frames silently
            shapes = [tuple(s.shape) for s in tif.series]
            raise InputError(
                f"'{path}': TIFF file holds {len(shapes)} image series (shapes "
                f"{', '.join(map(str, shapes[:4]))}{', ...' if len(shapes) > 4 else ''}); "
                "expected one (frames, rows, cols) stack"
            )
        series = tif.series[0]
        dtype = np.dtype(tif.byteorder + np.dtype(series.dtype).char)
        return tuple(series.shape), dtype, series.dataoffset


def load_stack(path: Path) -> np.ndarray:
    """A stack or map: a read-only memory map where possible, else the data in memory."""
    path = check_readable(path)
    try:
        if path.suffix.lower() == ".npy":
            return np.load(path, mmap_mode="r", allow_pickle=False)
        shape, dtype, offset = _tiff_layout(path)  # one image series, or an error
        if offset is None:  # compressed, tiled or scattered pages: not memory-mappable
            return tifffile.imread(path)
        return np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=shape)
    except InputError:
        raise
    except (OSError, ValueError) as exc:
        raise InputError(f"'{path}': cannot read: {one_line(exc)}") from exc


def default_adc_max(dtype) -> int:
    """Default ADC maximum (ADU) for stacks of ``dtype``.

    ``2**bits - 1`` for unsigned 8-, 16- and 32-bit integers; 65535 (a 16-bit ADC) for
    any other type, whose values are then checked against it.
    """
    dtype = np.dtype(dtype)
    if dtype.kind == "u" and dtype.itemsize <= 4:
        return int(np.iinfo(dtype).max)
    return 2**16 - 1


def describe_first(arr: np.ndarray, mask: np.ndarray, frame0: int) -> str:
    """The first value where ``mask`` holds, with its frame and pixel, for a message."""
    idx = tuple(int(i) for i in np.argwhere(mask)[0])
    value = arr[idx].item()  # a Python number: "600.5", not "np.float32(600.5)"
    idx = (idx[0] + frame0,) + idx[1:]
    if len(idx) == 3:
        return f"{value!r} at frame {idx[0]}, pixel ({idx[1]}, {idx[2]})"
    return f"{value!r} at pixel {idx}"


def needs_scan(dtype, adc_max: int | None) -> bool:
    """Whether values of ``dtype`` must be read to know they are counts ≤ ``adc_max``."""
    dtype = np.dtype(dtype)
    if dtype.kind != "u":
        return True
    return adc_max is not None and adc_max < np.iinfo(dtype).max


def check_counts(stack, path, *, adc_max: int | None = None, adc_bits_hint: str = "") -> None:
    """Check that a stack holds raw counts: non-negative integers, at most ``adc_max``.

    Only what the dtype does not already guarantee is scanned: an unsigned-integer
    stack needs no scan at all unless ``adc_max`` is below its type's maximum. Scans
    read a few million values at a time, so a memory-mapped stack is never loaded whole.

    Parameters
    ----------
    stack : ndarray, shape (frames, rows, cols)
        The stack (a memory map is fine).
    path : str or Path
        The file, named in the error message.
    adc_max : int, optional
        ADC maximum (ADU); values above it are an error.
    adc_bits_hint : str, optional
        Appended to the message about values above ``adc_max``.

    Raises
    ------
    InputError
        Naming the file, the problem and the first offending frame and pixel.
    """
    dtype = stack.dtype
    kind = dtype.kind
    if kind not in "uif" or dtype.itemsize > 8:
        raise InputError(f"'{path}': unsupported data type {dtype}; expected integer counts (ADU)")
    if not needs_scan(dtype, adc_max) or stack.size == 0:
        return
    per_frame = max(1, int(np.prod(stack.shape[1:])))
    step = max(1, _SCAN_ELEMENTS // per_frame)
    for f0 in range(0, stack.shape[0], step):
        chunk = np.asarray(stack[f0 : f0 + step])
        if kind == "f":
            bad = ~np.isfinite(chunk)
            if bad.any():
                raise InputError(
                    f"'{path}': contains NaN or infinite values ({describe_first(chunk, bad, f0)})"
                )
            bad = chunk != np.floor(chunk)
            if bad.any():
                raise InputError(
                    f"'{path}': float data that are not integer-valued "
                    f"({describe_first(chunk, bad, f0)}); counts must be raw ADU"
                )
        if kind in "if":
            bad = chunk < 0
            if bad.any():
                raise InputError(
                    f"'{path}': negative values ({describe_first(chunk, bad, f0)}); counts must be "
                    "raw ADU, never offset-subtracted"
                )
        if adc_max is not None:
            bad = chunk > adc_max
            if bad.any():
                raise InputError(
                    f"'{path}': values above the ADC maximum {adc_max} "
                    f"({describe_first(chunk, bad, f0)}){adc_bits_hint}"
                )


def read_stack(path, *, adc_max: int | None = None) -> np.ndarray:
    """Read a (frames, rows, cols) stack of raw counts, checked.

    Parameters
    ----------
    path : str or Path
        A TIFF (``.tif``/``.tiff``) or ``.npy`` file.
    adc_max : int, optional
        ADC maximum (ADU); values above it are an error.

    Returns
    -------
    ndarray, shape (frames, rows, cols)
        A read-only memory map where the file allows it, else an in-memory array; the
        file's dtype.

    Raises
    ------
    InputError
        Missing or unreadable file, not 3-D, not numeric, or values that are not raw
        counts (NaN, negative, non-integer, above ``adc_max``); the message names the file.
    """
    path = Path(path)
    stack = load_stack(path)
    if stack.ndim != 3:
        raise InputError(
            f"'{path}': not a 3-D (frames, rows, cols) stack: shape {tuple(stack.shape)}"
        )
    check_counts(stack, path, adc_max=adc_max)
    return stack


def read_map(
    path,
    shape,
    *,
    name: str = "map",
    positive: bool = False,
    nonnegative: bool = False,
) -> np.ndarray:
    """Read a per-pixel (rows, cols) map as float64, checked.

    Parameters
    ----------
    path : str or Path
        A TIFF or ``.npy`` file holding a 2-D image (leading axes of length 1 are
        dropped).
    shape : tuple of int
        Expected (rows, cols), those of the stacks.
    name : str, optional
        What the map is (``"offset"``, ``"read_noise"``, ``"e_per_adu"``), for messages.
    positive, nonnegative : bool, optional
        Require every value > 0, or ≥ 0.

    Returns
    -------
    ndarray of float64, shape (rows, cols)

    Raises
    ------
    InputError
        Missing or unreadable file, wrong shape, NaN or infinite values, or values out of
        range; the message names the file.
    """
    path = Path(path)
    data = np.asarray(load_stack(path))
    while data.ndim > 2 and data.shape[0] == 1:
        data = data[0]
    if data.dtype.kind not in "uif":
        raise InputError(f"'{path}': {name} map has unsupported data type {data.dtype}")
    shape = tuple(int(d) for d in shape)
    if data.shape != shape:
        raise InputError(
            f"'{path}': {name} map has shape {tuple(data.shape)}, but the stacks are "
            f"{shape} (rows, cols)"
        )
    data = data.astype(np.float64)
    bad = ~np.isfinite(data)
    if bad.any():
        raise InputError(
            f"'{path}': {name} map contains NaN or infinite values ({describe_first(data, bad, 0)})"
        )
    if positive and np.any(data <= 0):
        raise InputError(
            f"'{path}': {name} map must be > 0 everywhere ({describe_first(data, data <= 0, 0)})"
        )
    if nonnegative and np.any(data < 0):
        raise InputError(
            f"'{path}': {name} map must be >= 0 everywhere ({describe_first(data, data < 0, 0)})"
        )
    return data


