"""TIFF stacks (plain, ImageJ, OME and Micro-Manager TIFF): one reader of the registry of
:mod:`emccdcal.data.stacks`.

The frames of most camera TIFFs are one contiguous block: the header gives its place
(:func:`header`), and the stacks module maps or reads it directly. Compressed, tiled or
scattered pages are decoded by tifffile (:func:`open_stack`). tifffile logs a damaged page
instead of raising; those messages are caught here: a broken page index is an error (its
frames cannot all be found), a damaged metadata tag a warning (the frames are sound).
Micro-Manager's camera properties are read by :mod:`emccdcal.data.micromanager`.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import re
import warnings
from pathlib import Path

import numpy as np
import tifffile

from .._util import one_line
from ..defaults import WITHOUT_EM_REGISTER
from ..errors import InputError, InputWarning
from .extent import check_data_fits
from .settings import CameraSettings

__all__ = ["SUFFIXES", "header", "settings", "open_stack"]

#: File name suffixes of this format.
SUFFIXES = (".tif", ".tiff")


def header(path: Path):
    """Shape, dtype (in the file's byte order), data offset (None where the frames are not
    one contiguous block) and frame stride (None: frames back to back) of the TIFF's one
    image series. A damaged metadata tag is warned about once per file version."""
    shape, dtype, offset, log = _tiff_layout(path)
    if log and _first_time(path):  # e.g. a damaged metadata tag: the frames are sound
        warnings.warn(
            f"'{path}': damaged TIFF: {log[0]}"
            f"{f' (and {len(log) - 1} more)' if len(log) > 1 else ''}; its frames "
            "were read in full",
            InputWarning,
            stacklevel=4,
        )
    return shape, dtype, offset, None


def settings(path: Path) -> CameraSettings:
    """The camera settings a Micro-Manager or OME TIFF records; none for a plain TIFF.
    Micro-Manager's properties first; what they leave unsaid, the OME-XML's detector."""
    import dataclasses

    from . import micromanager, ome

    with _tifffile_log(path), tifffile.TiffFile(path) as tif:
        recorded = micromanager.stack_settings(path, tif)
        described = ome.settings_of(tif.ome_metadata) if tif.is_ome else CameraSettings()
    more = {
        name: getattr(described, name)
        for name in CameraSettings.names()
        if getattr(recorded, name) is None and getattr(described, name) is not None
    }
    if not more:
        return recorded
    if more.get("camera_kind") in WITHOUT_EM_REGISTER:  # its gain field is no EM set-point
        more["em_gain_setpoint"] = None
    return dataclasses.replace(recorded, **more)


def open_stack(path: Path) -> np.ndarray:
    """Compressed, tiled or scattered pages, decoded into memory. tifffile logs a page it
    cannot decode and fills it with zeros: that is an error here."""
    with _tifffile_log(path) as log, tifffile.TiffFile(path) as tif:
        _check_strips(path, tif)
        data = tif.series[0].asarray()
    if log:
        raise InputError(f"'{path}': cannot read: {log[0]}")
    return data


_WARNED: set = set()


def _first_time(path: Path) -> bool:
    """Whether this version of the file has not been warned about yet (in this process)."""
    st = path.stat()
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    if key in _WARNED:
        return False
    _WARNED.add(key)
    return True


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
            check_data_fits(Path(path), shape, dtype, offset)
        if broken:
            raise InputError(f"'{path}': damaged TIFF: {broken[0]}; its frames cannot all be found")
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
        spans.append(
            (
                page.offset,
                page.offset + fmt.tagnosize + n_tags * fmt.tagsize + fmt.offsetsize,
                f"page {i}'s tag list",
            )
        )
        for tag in page.tags.values():
            if tag.valuebytecount > fmt.tagoffsetthreshold:  # stored outside the list
                spans.append(
                    (
                        tag.valueoffset,
                        tag.valueoffset + tag.valuebytecount,
                        f"page {i}'s {tag.name}",
                    )
                )
        spans += [
            (o, o + c, f"page {i}'s data")
            for o, c in zip(page.dataoffsets, page.databytecounts)
            if c
        ]
    spans.sort()
    for (_, end, what), (start, _, other) in zip(spans, spans[1:]):
        if start < end and "data" in what + other:
            raise InputError(f"'{path}': damaged TIFF: {what} and {other} overlap (byte {start})")


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
        raise InputError(
            f"'{path}': damaged TIFF: its first page describes {shape[0]} "
            f"frames but the file has {n} pages"
        )
    for i in checked:
        found = pages[i].dataoffsets[0] if pages[i].dataoffsets else None
        if found != offset + i * frame:
            raise InputError(
                f"'{path}': damaged TIFF: frame {i}'s data are at byte "
                f"{found}, not at {offset + i * frame} where its first page "
                "puts them"
            )
