"""Readers of stacks and maps: shape and dtype from the header, data read lazily.

One interface for every format (docs/formats.md): :func:`stack_header` (shape, dtype),
:func:`load_stack` (a lazy array: a memory map, or an object that reads what is sliced),
:func:`read_band` (rows of every frame, read into memory: what a calibration's tiles do)
and :func:`stack_settings` (:class:`~emccdcal.data.settings.CameraSettings`). Every format
is a reader module (TIFF, ``.npy``, SPE, SIF, FITS, Zarr), registered by the suffixes it
declares (``_READER_MODULES``); where its frames lie at regular places in the file they
are memory-mapped or read with ``preadv`` here, else the module's ``open_stack`` reads
them. Counts, offsets and read noise are in ADU. Every problem is an
:class:`~emccdcal.errors.InputError` whose one-line message names the file.
"""

from __future__ import annotations

import dataclasses
import operator
import os
import re
from pathlib import Path

import numpy as np

from .. import plugins
from .._util import one_line
from ..errors import InputError, MissingFileError
from .extent import check_data_fits
from .settings import CameraSettings

__all__ = [
    "read_stack",
    "read_map",
    "load_stack",
    "read_band",
    "stack_header",
    "stack_settings",
    "check_readable",
    "describe_missing",
    "describe_first",
    "check_counts",
    "content_fingerprint",
    "needs_scan",
    "default_adc_max",
    "STACK_SUFFIXES",
]

#: Elements read at a time when scanning a stack's values.
_SCAN_ELEMENTS = 2**23


#: Bytes of whole frames :func:`read_band` reads per system call.
_READ_BYTES = 2**24


def read_band(
    path, first_row: int, stop_row: int, skip_frames: int = 0, stop_frame: int | None = None
) -> np.ndarray:
    """Rows ``first_row:stop_row`` of every frame from ``skip_frames`` on (up to
    ``stop_frame``, exclusive, where given), read into memory.

    Only those bytes are read (one ``preadv`` per frame, or per 16 MB of whole frames),
    so reading a band of a large
    stack neither loads the file nor maps it: a memory map would count the pages the
    kernel maps around every touched row (64 kB per frame) in the process's resident
    memory. Compressed or scattered TIFF data are read through tifffile instead.

    Returns
    -------
    ndarray, shape (stop_frame - skip_frames, stop_row - first_row, cols)
        The file's dtype (possibly non-native byte order), raw counts.
    """
    path = check_readable(Path(path))
    layout = _raw_layout(path)
    if layout is None:
        return np.asarray(load_stack(path)[skip_frames:stop_frame, first_row:stop_row])
    shape, dtype, offset, stride = layout
    frames, rows, cols = shape
    if stop_frame is not None:
        frames = max(0, min(frames, stop_frame))
    first_row, stop_row = max(0, first_row), min(rows, stop_row)
    row_bytes = cols * dtype.itemsize
    frame_bytes = rows * row_bytes
    out = np.empty((max(0, frames - skip_frames), stop_row - first_row, cols), dtype=dtype)
    flat = out.reshape(out.shape[0], -1).view(np.uint8)
    want = flat.shape[1]
    # Whole frames back to back in the file: many per call. A band, or frames with
    # metadata between them (SPE), are scattered: one call per frame.
    per_call = max(1, _READ_BYTES // frame_bytes) if want == frame_bytes == stride else 1
    fd = os.open(path, os.O_RDONLY)
    try:
        for i in range(0, out.shape[0], per_call):
            part = flat[i : i + per_call]
            at = offset + (skip_frames + i) * stride + first_row * row_bytes
            got = os.preadv(fd, [part], at)
            if got != part.nbytes:
                raise InputError(
                    f"'{path}': file ends inside frame {skip_frames + i + got // want}: truncated"
                )
    finally:
        os.close(fd)
    return out


def _raw_layout(path: Path):
    """(shape, dtype, data offset, frame stride in bytes) of a 3-D stack whose frames are
    C-ordered blocks at regular places in the file, else None."""
    layout = _layout(path)
    return None if layout[2] is None or len(layout[0]) != 3 else layout


def _layout(path: Path):
    """Shape, dtype (in the file's byte order), data offset (None where the data are not
    C-ordered blocks at regular places) and frame stride (bytes from one frame to the
    next; None for a map) of a stack or map, from its header; the data must fit in the
    file."""
    try:
        shape, dtype, offset, stride = _header(_reader(path).header(path))
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - a damaged file can break a parser anywhere
        raise InputError(f"'{path}': cannot read: {_reason(exc)}") from exc
    if len(shape) == 3 and shape[0] == 0:
        raise InputError(f"'{path}': holds no frames (a stack of 0 × {shape[1]} × {shape[2]})")
    if offset is not None and len(shape) == 3 and stride is None:
        stride = shape[1] * shape[2] * dtype.itemsize
    if offset is not None:
        check_data_fits(path, shape, dtype, offset, stride)
    return shape, dtype, offset, stride


def _header(header):
    """A reader's header (shape, dtype, offset, stride) checked and made exact (a reader
    may be another package's: its dtype given as text, its numbers as NumPy's); a
    ValueError, said as the file's, where it is not one."""
    shape, dtype, offset, stride = header
    shape = tuple(operator.index(n) for n in shape)
    if len(shape) not in (2, 3) or min(shape) < 0 or 0 in shape[-2:]:
        raise ValueError(f"its reader gives the shape {shape}, not (frames,) rows, cols")
    dtype = np.dtype(dtype)
    if dtype.kind not in "uif":
        raise ValueError(f"its reader gives the data type {dtype}, not numbers")
    offset = None if offset is None else operator.index(offset)
    stride = None if stride is None else operator.index(stride)
    if (offset is not None and offset < 0) or (stride is not None and stride <= 0):
        raise ValueError(f"its reader gives the data offset {offset} and frame stride {stride}")
    return shape, dtype, offset, stride


#: How a file's name states its EM-gain set-point where the file records none
#: (``25x-gain.tif``, ``gain_25.tif``): the one rule of ``scan``, ``apply``, ``gain-check``
#: and the napari reader.
SETPOINT_IN_NAME = (
    re.compile(r"(?<![\d.])(\d+(?:\.\d+)?)\s*x(?![a-z])", re.IGNORECASE),
    re.compile(r"gain[-_ ]?(\d+(?:\.\d+)?)", re.IGNORECASE),
)


def setpoint_in_name(path) -> float | None:
    """The EM-gain set-point a file's name states (:data:`SETPOINT_IN_NAME`), or None.

    Examples
    --------
    >>> setpoint_in_name("darks-300x.tif"), setpoint_in_name("gain_25.tif"), setpoint_in_name("a.tif")
    (300.0, 25.0, None)
    """
    stem = Path(path).stem
    for pattern in SETPOINT_IN_NAME:
        match = pattern.search(stem)
        if match:
            return float(match.group(1))
    return None


def stack_settings(path, *, setpoint_from_name: bool = False) -> CameraSettings:
    """The camera settings a stack's file records (:class:`CameraSettings`; fields the
    format or the file does not hold are None); with ``setpoint_from_name``, the
    set-point its name states where the file records none (:func:`setpoint_in_name`)."""
    path = check_readable(Path(path))
    _layout(path)  # a readable stack first
    try:
        settings = _reader(path).settings(path)
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - a damaged file can break a parser anywhere
        raise InputError(f"'{path}': cannot read its settings: {_reason(exc)}") from exc
    if not isinstance(settings, CameraSettings):  # another package's reader, mistaken
        raise InputError(
            f"'{path}': its reader gives its settings as {type(settings).__name__}, not "
            "CameraSettings"
        )
    if setpoint_from_name and settings.em_gain_setpoint is None:
        named = setpoint_in_name(path)
        if named is not None and named >= 1:
            settings = dataclasses.replace(settings, em_gain_setpoint=named)
    return settings


#: The readers, by entry point of the group ``emccdcal.readers`` (:mod:`emccdcal.plugins`):
#: the package's own (a module each here) and any other package's. Each declares its
#: ``SUFFIXES`` and ``header(path)`` (shape, dtype, data offset, frame stride: the offset
#: None where the frames are not blocks at regular places, the stride None where they lie
#: back to back) and ``settings(path)`` (:class:`CameraSettings`); where ``header`` can
#: give no offset, also ``open_stack(path)`` (a lazy array). A new format is a module
#: and its entry point: nothing else lists formats.
_READERS = {
    suffix: reader
    for reader in plugins.load(plugins.READERS).values()
    for suffix in reader.SUFFIXES
}
#: File name suffixes of stacks and maps that can be read.
STACK_SUFFIXES = tuple(_READERS)


def _reader(path: Path):
    """The reader module of ``path``'s format (by its suffix)."""
    try:
        return _READERS[path.suffix.lower()]
    except KeyError:
        if not _READERS:  # the entry points are in the installed package's metadata
            raise InputError(
                f"'{path}': no reader is registered: emccdcal's entry points "
                "are missing (install it: pip install -e .)"
            ) from None
        raise InputError(
            f"'{path}': unsupported file type '{path.suffix}' "
            f"(supported: {', '.join(STACK_SUFFIXES)})"
        ) from None


def describe_missing(path: Path, what: str = "file") -> str:
    """``"<what> not found: '<path>' (resolved to '<absolute path>')"``."""
    return f"{what} not found: '{path}' (resolved to '{Path(path).expanduser().resolve()}')"


def check_readable(path: Path) -> Path:
    """``path`` if it is an existing file of a supported type, else an InputError."""
    path = Path(path)
    if path.is_symlink() and not path.exists():
        raise InputError(f"'{path}': a symbolic link to nothing (or to itself)")
    if not path.exists():
        raise MissingFileError(describe_missing(path))
    if not path.is_file() and not path.is_dir():  # a pipe or a device: reading could block
        raise InputError(f"'{path}' is not a regular file (a pipe, socket or device)")
    if path.is_dir() and path.suffix.lower() != ".zarr":  # a Zarr store is a directory
        raise InputError(f"'{path}' is a directory, not a file")
    _reader(path)  # a supported format
    return path


def stack_header(path: Path) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of a stack or map from its header, without reading the data."""
    shape, dtype, *_ = _layout(check_readable(path))
    return shape, dtype


def load_stack(path: Path) -> np.ndarray:
    """A stack or map: a read-only memory map where possible, else the data in memory."""
    path = check_readable(path)
    shape, dtype, offset, stride = _layout(path)  # a TIFF: one image series, or an error
    try:
        if offset is not None and (stride is None or stride == np.prod(shape[1:]) * dtype.itemsize):
            return np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=shape)
        if offset is not None:  # frames with metadata between them: a strided view
            frame = int(np.prod(shape[1:])) * dtype.itemsize
            raw = np.memmap(
                path,
                dtype=np.uint8,
                mode="r",
                offset=offset,
                shape=((shape[0] - 1) * stride + frame,),
            )
            return np.ndarray(
                shape,
                dtype=dtype,
                buffer=raw,
                strides=(stride, shape[2] * dtype.itemsize, dtype.itemsize),
            )
        stack = _reader(path).open_stack(path)
        if tuple(getattr(stack, "shape", ())) != tuple(shape):
            raise InputError(
                f"'{path}': its reader opens an array of shape "
                f"{tuple(getattr(stack, 'shape', ()))} where its header says {tuple(shape)}"
            )
        return stack
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - a damaged file can break a parser anywhere
        raise InputError(f"'{path}': cannot read: {_reason(exc)}") from exc


def _reason(exc: BaseException) -> str:
    """One line for an exception a parser raised on a damaged file: its message, or for a
    bare internal error (a TypeError deep in a parser) its kind."""
    if isinstance(exc, (OSError, ValueError, EOFError)):
        return one_line(exc)
    return f"the file is damaged ({type(exc).__name__}: {one_line(exc)})"


def content_fingerprint(path: Path, *, samples: int = 8, size: int = 4096) -> str:
    """A digest of a file's size and of ``samples`` blocks of ``size`` bytes spread over it.

    Copies of a file agree; two acquisitions of a camera, whose counts differ from frame
    to frame, differ in every block. Reads 32 kB, whatever the file's size.
    """
    import hashlib

    if path.is_dir():  # a Zarr store: its files' names and sizes, and samples of them
        files = sorted(p for p in path.rglob("*") if p.is_file())
        digest = hashlib.blake2b(digest_size=16)
        for p in files:
            digest.update(f"{p.relative_to(path)}:{p.stat().st_size};".encode())
        for p in files[:: max(1, len(files) // samples)]:
            digest.update(p.read_bytes()[:size])
        return digest.hexdigest()
    n = path.stat().st_size
    digest = hashlib.blake2b(str(n).encode(), digest_size=16)
    with open(path, "rb") as fh:
        for k in range(samples):
            fh.seek(max(0, (n - size) * k // max(1, samples - 1)))
            digest.update(fh.read(size))
    return digest.hexdigest()


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
