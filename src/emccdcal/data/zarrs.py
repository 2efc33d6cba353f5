"""Zarr stacks: a (frames, rows, cols) array, read by chunks (the ``zarr`` extra).

Zarr has no camera conventions; a store's settings are read from its attribute
``"emccdcal"``, a mapping with the field names of
:class:`~emccdcal.data.settings.CameraSettings` (e.g. ``{"em_gain_setpoint": 300,
"readout_rate_mhz": 10}``), which :func:`emccdcal.data.stacks.stack_settings` returns.
"""

from __future__ import annotations

from pathlib import Path

from .._util import one_line
from ..errors import InputError
from .settings import CameraSettings

__all__ = ["SUFFIXES", "ATTRIBUTE", "open_array", "header", "open_stack", "settings"]

#: File name suffixes of this format.
SUFFIXES = (".zarr",)

#: The attribute holding a store's camera settings.
ATTRIBUTE = "emccdcal"


def open_array(path: Path):
    """The store's array, read-only and lazy (slicing reads only the chunks it touches)."""
    try:
        import zarr
    except ImportError:
        raise InputError("reading Zarr needs the 'zarr' extra: pip install 'emccdcal[zarr]'") from None
    try:
        arr = zarr.open(str(path), mode="r")
    except Exception as exc:  # noqa: BLE001 - a damaged store can fail anywhere
        raise InputError(f"'{path}': not a Zarr array: {one_line(exc)}") from None
    if not hasattr(arr, "shape") or not hasattr(arr, "dtype"):
        raise InputError(f"'{path}': a Zarr group, not an array; point at the stack's array")
    return arr


def settings(path: Path) -> CameraSettings:
    """The settings recorded in the store's ``"emccdcal"`` attribute (unknown names are
    an error, so that a misspelt one is not silently dropped)."""
    recorded = dict(open_array(path).attrs.get(ATTRIBUTE, {}))
    unknown = sorted(set(recorded) - set(CameraSettings.names()))
    if unknown:
        raise InputError(f"'{path}': unknown camera setting(s) {', '.join(unknown)} in its "
                         f"'{ATTRIBUTE}' attribute (known: {', '.join(CameraSettings.names())})")
    for key in ("roi", "binning"):
        if recorded.get(key) is not None:
            recorded[key] = tuple(int(v) for v in recorded[key])
    return CameraSettings(**recorded)


def header(path: Path):
    """Shape, dtype, and no offset or stride: a store is read by chunks."""
    arr = open_array(path)
    return tuple(arr.shape), arr.dtype, None, None


open_stack = open_array
