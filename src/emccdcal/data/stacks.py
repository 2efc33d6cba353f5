"""Readers of stacks and maps: shape and dtype from the header, data read lazily.

One interface for every format (docs/formats.md): :func:`stack_header` (shape, dtype),
:func:`load_stack` (a lazy array: a memory map, or an object that reads what is sliced),
:func:`read_band` (rows of every frame, read into memory: what a calibration's tiles do)
and :func:`stack_settings` (:class:`~emccdcal.data.settings.CameraSettings`). TIFF and
``.npy`` are read here (memory-mapped / ``preadv`` where the frames lie at regular
places); SPE, SIF, FITS and Zarr by a module each (``header``, ``settings``,
``open_stack``). Counts, offsets and read noise are in ADU. Every problem is an
:class:`~emccdcal.errors.InputError` whose one-line message names the file.
"""

from __future__ import annotations

import contextlib
import functools
import importlib
import logging
import os
import re
import warnings
from pathlib import Path

import numpy as np
import tifffile

from .._util import one_line
from ..errors import InputError, InputWarning, MissingFileError
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

#: File name suffixes of stacks and maps that can be read.
STACK_SUFFIXES = (".tif", ".tiff", ".npy", ".spe", ".sif", ".fits", ".fit", ".fts", ".zarr")

#: Elements read at a time when scanning a stack's values.
_SCAN_ELEMENTS = 2**23


#: Bytes of whole frames :func:`read_band` reads per system call.
_READ_BYTES = 2**24


def read_band(path, first_row: int, stop_row: int, skip_frames: int = 0,
              stop_frame: int | None = None) -> np.ndarray:
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
            part = flat[i:i + per_call]
            at = offset + (skip_frames + i) * stride + first_row * row_bytes
            got = os.preadv(fd, [part], at)
            if got != part.nbytes:
                raise InputError(f"'{path}': file ends inside frame "
                                 f"{skip_frames + i + got // want}: truncated")
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
    log, stride = (), None
    try:
        fmt = _format(path)
        if fmt is not None:
            shape, dtype, offset, stride = fmt.header(path)
        elif path.suffix.lower() == ".npy":
            shape, dtype, offset = _npy_layout(path)
        else:
            shape, dtype, offset, log = _tiff_layout(path)
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - a damaged file can break a parser anywhere
        raise InputError(f"'{path}': cannot read: {_reason(exc)}") from exc
    if offset is not None and len(shape) == 3 and stride is None:
        stride = shape[1] * shape[2] * dtype.itemsize
    if offset is not None:
        _check_data_fits(path, shape, dtype, offset, stride)
    if log and _first_time(path):  # e.g. a damaged metadata tag: the frames are sound
        warnings.warn(f"'{path}': damaged TIFF: {log[0]}"
                      f"{f' (and {len(log) - 1} more)' if len(log) > 1 else ''}; its frames "
                      "were read in full", InputWarning, stacklevel=3)
    return shape, dtype, offset, stride


def stack_settings(path) -> CameraSettings:
    """The camera settings a stack's file records (:class:`CameraSettings`; fields the
    format or the file does not hold are None)."""
    path = check_readable(Path(path))
    fmt = _format(path)
    if fmt is not None:
        return fmt.settings(path)
    if path.suffix.lower() in (".tif", ".tiff"):
        from . import micromanager

        _layout(path)  # a readable stack first
        with _tifffile_log(path), tifffile.TiffFile(path) as tif:
            return micromanager.stack_settings(path, tif)
    return CameraSettings()


#: Formats read by a module of their own, each with ``header(path)`` (shape, dtype, data
#: offset, frame stride), ``settings(path)`` and, where the offset is None (the data are
#: not mapped here), ``open_stack(path)``: a lazy array.
_FORMATS = {".spe": "spe", ".sif": "sif", ".fits": "fits", ".fit": "fits", ".fts": "fits",
            ".zarr": "zarrs"}


def _format(path: Path):
    name = _FORMATS.get(path.suffix.lower())
    return None if name is None else importlib.import_module(f".{name}", __package__)


_WARNED: set = set()


def _first_time(path: Path) -> bool:
    """Whether this version of the file has not been warned about yet (in this process)."""
    st = path.stat()
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    if key in _WARNED:
        return False
    _WARNED.add(key)
    return True


def _npy_layout(path: Path):
    with open(path, "rb") as fh:
        fmt = np.lib.format
        version = fmt.read_magic(fh)
        read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        shape, fortran, dtype = read(fh)
        offset = fh.tell()
    if dtype.hasobject:
        raise InputError(f"'{path}': holds Python objects, not numbers")
    # A .npy file is its header and its data, nothing after: a damaged header length
    # (which moves the data) shows as bytes left over, or missing (_check_data_fits).
    extra = path.stat().st_size - offset - int(np.prod(shape)) * dtype.itemsize
    if extra > 0:
        raise InputError(f"'{path}': damaged .npy file: {extra} bytes after the "
                         f"{' × '.join(map(str, shape))} values its header describes")
    return tuple(shape), dtype, (None if fortran and len(shape) > 1 else offset)


def _check_data_fits(path: Path, shape, dtype, offset: int, stride: int | None = None) -> None:
    """A truncated file: one line saying how much of it is there."""
    size = path.stat().st_size
    frame = int(np.prod(shape[1:])) * dtype.itemsize if len(shape) == 3 else 0
    if stride is not None and shape[0]:
        need = offset + (shape[0] - 1) * stride + frame
    else:
        need = offset + int(np.prod(shape)) * dtype.itemsize
    if need <= size:
        return
    what = " × ".join(str(d) for d in shape)
    whole = ""
    if frame:
        step = stride or frame
        whole = f": {max(0, size - offset + step - frame) // step} whole frame(s) of {shape[0]}"
    raise InputError(f"'{path}': truncated: its header describes {what} values of "
                     f"{dtype.itemsize} bytes from byte {offset}, {need} bytes, but the file "
                     f"has {size}{whole}")


_MICROMANAGER_HEADER = ("summary", "index map", "display settings", "comments")


@contextlib.contextmanager
def _tifffile_log(path):
    """Capture tifffile's log records while it reads ``path`` (it logs damaged pages
    instead of raising): yields the list of their messages."""
    messages: list[str] = []

    class Catch(logging.Handler):
        def emit(self, record):  # "<tifffile.TiffPages @8> invalid page offset 6656"
            message = one_line(re.sub(r"^<[^>]*>\s*", "", record.getMessage()))
            # tifffile's parse of a Micro-Manager file header, which OME-TIFFs carrying
            # Micro-Manager tags (from other writers) lack: metadata, not the frames
            if not any(part in message for part in _MICROMANAGER_HEADER):
                messages.append(message)

    logger = logging.getLogger("tifffile")
    handler, propagate = Catch(logging.WARNING), logger.propagate
    logger.addHandler(handler)
    logger.propagate = False  # nothing reaches the root logger's stderr handler
    try:
        yield messages
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate


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
    if path.suffix.lower() not in STACK_SUFFIXES:
        raise InputError(
            f"'{path}': unsupported file type '{path.suffix}' "
            f"(supported: {', '.join(STACK_SUFFIXES)})"
        )
    return path


def stack_header(path: Path) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of a stack or map from its header, without reading the data."""
    shape, dtype, *_ = _layout(check_readable(path))
    return shape, dtype


def _tiff_layout(path: Path):
    """Shape, dtype (in the file's byte order) and offset of the data of a TIFF's one
    image series; the offset is None where the data are not one contiguous block.

    Finding them walks the file's page index (about 20 ms for 5000 frames), which a
    calibration would otherwise do several times per stack: it is done once per file
    version (path, size, modification time). Also returns what tifffile logged about
    damaged pages (:func:`_layout` issues it as an :class:`~emccdcal.errors.InputWarning`).
    """
    st = path.stat()
    return _tiff_layout_cached(str(path.resolve()), st.st_size, st.st_mtime_ns)


@functools.lru_cache(maxsize=128)
def _tiff_layout_cached(path: str, size: int, mtime_ns: int):
    with _tifffile_log(path) as log, tifffile.TiffFile(path) as tif:
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
        shape, offset = tuple(series.shape), series.dataoffset
        # A broken page index hides frames: whether those pages held frames of the
        # stack cannot be known, so the stack cannot be trusted to be complete.
        broken = [m for m in log if "page" in m.lower()]
        if broken and offset is not None:  # say so when it is a truncation
            _check_data_fits(Path(path), shape, dtype, offset)
        if broken:
            raise InputError(f"'{path}': damaged TIFF: {broken[0]}; its frames cannot all "
                             "be found")
        if offset is not None:
            _check_strips(path, tif, pages=[0])
            if len(shape) == 3:
                _check_page_index(path, tif, shape, dtype, offset)
        return shape, dtype, offset, tuple(log)


def _check_strips(path, tif, pages=None) -> None:
    """Data that overlap other data or the file's own structure (its header, a page's
    tag list or a tag's value): a damaged page index (a moved offset or a longer byte
    count), which would otherwise read bytes that are not counts, or another frame's.
    ``pages``: the indices of the pages to check (default all)."""
    fmt = tif.tiff
    spans = [(0, 16 if fmt.offsetsize == 8 else 8, "the file header")]
    for i in range(len(tif.pages)) if pages is None else pages:
        page = tif.pages[i]
        n_tags = len(page.tags)
        spans.append((page.offset, page.offset + fmt.tagnosize + n_tags * fmt.tagsize
                      + fmt.offsetsize, f"page {i}'s tag list"))
        for tag in page.tags.values():
            if tag.valuebytecount > fmt.tagoffsetthreshold:  # stored outside the list
                spans.append((tag.valueoffset, tag.valueoffset + tag.valuebytecount,
                              f"page {i}'s {tag.name}"))
        spans += [(o, o + c, f"page {i}'s data")
                  for o, c in zip(page.dataoffsets, page.databytecounts) if c]
    spans.sort()
    for (_, end, what), (start, _, other) in zip(spans, spans[1:]):
        if start < end and "data" in what + other:
            raise InputError(f"'{path}': damaged TIFF: {what} and {other} overlap "
                             f"(byte {start})")


def _check_page_index(path, tif, shape, dtype, offset) -> None:
    """The frames of a contiguous stack are read from the first page's data offset on;
    that offset, the frame size and the number of frames come from its first page (or its
    description). The page index must agree: one page per frame, the second and the last
    page's data where the layout puts them. A damaged first page otherwise moves or
    reshapes every frame without a word."""
    frame = shape[1] * shape[2] * dtype.itemsize
    pages = tif.pages
    pages.useframes = True  # light page objects: only their data offsets are needed
    n = len(pages)
    if n == 1:  # one page holding every frame
        checked = [0]
    elif n == shape[0]:
        checked = sorted({0, 1, n - 1})
    else:
        raise InputError(f"'{path}': damaged TIFF: its first page describes {shape[0]} "
                         f"frames but the file has {n} pages")
    for i in checked:
        found = pages[i].dataoffsets[0] if pages[i].dataoffsets else None
        if found != offset + i * frame:
            raise InputError(f"'{path}': damaged TIFF: frame {i}'s data are at byte "
                             f"{found}, not at {offset + i * frame} where its first page "
                             "puts them")


def load_stack(path: Path) -> np.ndarray:
    """A stack or map: a read-only memory map where possible, else the data in memory."""
    path = check_readable(path)
    shape, dtype, offset, stride = _layout(path)  # a TIFF: one image series, or an error
    try:
        if offset is not None and (stride is None or stride == np.prod(shape[1:]) * dtype.itemsize):
            return np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=shape)
        if offset is not None:  # frames with metadata between them: a strided view
            frame = int(np.prod(shape[1:])) * dtype.itemsize
            raw = np.memmap(path, dtype=np.uint8, mode="r", offset=offset,
                            shape=((shape[0] - 1) * stride + frame,))
            return np.ndarray(shape, dtype=dtype, buffer=raw,
                              strides=(stride, shape[2] * dtype.itemsize, dtype.itemsize))
        if path.suffix.lower() == ".npy":  # Fortran order
            return np.load(path, mmap_mode="r", allow_pickle=False)
        fmt = _format(path)
        if fmt is not None:
            return fmt.open_stack(path)
        # Compressed, tiled or scattered pages: decoded into memory. tifffile logs a page
        # it cannot decode and fills it with zeros: that is an error here.
        with _tifffile_log(path) as log, tifffile.TiffFile(path) as tif:
            _check_strips(path, tif)
            data = tif.series[0].asarray()
        if log:
            raise InputError(f"'{path}': cannot read: {log[0]}")
        return data
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


