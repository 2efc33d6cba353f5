"""NumPy ``.npy`` stacks and maps: one reader of the registry of :mod:`emccdcal.data.stacks`.

A ``.npy`` file is its header and its data, nothing after: C-ordered data are mapped or
read where they lie; Fortran-ordered ones through :func:`numpy.load` (memory-mapped). The
format records no camera settings.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .settings import CameraSettings

__all__ = ["SUFFIXES", "header", "settings", "open_stack"]

#: File name suffixes of this format.
SUFFIXES = (".npy",)


def header(path: Path):
    """Shape, dtype, data offset (None for Fortran order) and frame stride (None)."""
    return (*_npy_layout(path), None)


def settings(path: Path) -> CameraSettings:
    """Nothing: a ``.npy`` file records no camera settings."""
    return CameraSettings()


def open_stack(path: Path) -> np.ndarray:
    """Fortran-ordered data, memory-mapped."""
    return np.load(path, mmap_mode="r", allow_pickle=False)


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
        raise InputError(
            f"'{path}': damaged .npy file: {extra} bytes after the "
            f"{' × '.join(map(str, shape))} values its header describes"
        )
    return tuple(shape), dtype, (None if fortran and len(shape) > 1 else offset)
