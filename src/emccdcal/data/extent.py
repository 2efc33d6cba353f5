"""Where a stack's data lie in its file, checked against the file's size (every reader)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError

__all__ = ["check_data_fits"]


def check_data_fits(path: Path, shape, dtype, offset: int, stride: int | None = None) -> None:
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
    raise InputError(
        f"'{path}': truncated: its header describes {what} values of "
        f"{dtype.itemsize} bytes from byte {offset}, {need} bytes, but the file "
        f"has {size}{whole}"
    )
