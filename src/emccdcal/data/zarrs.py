"""Zarr stacks: a (frames, rows, cols) array, read by chunks (the ``zarr`` extra).

A store is an array, or an OME-Zarr image (OME-NGFF: a group whose ``multiscales``
attribute names its arrays; the first, full-resolution one is read, with axes
``t, y, x``). Zarr has no camera conventions; a store's settings are read from the
attribute ``"emccdcal"`` (of the array, else of the image's group), a mapping with the
field names of :class:`~emccdcal.data.settings.CameraSettings` (e.g.
``{"em_gain_setpoint": 300, "readout_rate_mhz": 10}``), else from the Micro-Manager
properties the group records under ``"micromanager"`` (``<camera>-<property>`` names, as
``emccdcal acquire`` writes them), which :func:`emccdcal.data.stacks.stack_settings`
returns.
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
    return _open(path)[0]


def _open(path: Path):
    """(the store's array, the attributes of the OME-Zarr group holding it, or {})."""
    try:
        import zarr
    except ImportError:
        raise InputError("reading Zarr needs the 'zarr' extra: pip install 'emccdcal[zarr]'") from None
    try:
        node = zarr.open(str(path), mode="r")
    except Exception as exc:  # noqa: BLE001 - a damaged store can fail anywhere
        raise InputError(f"'{path}': not a Zarr array: {one_line(exc)}") from None
    if hasattr(node, "shape") and hasattr(node, "dtype"):
        return node, {}
    image = _image_path(node)
    if image is None:
        raise InputError(f"'{path}': a Zarr group that is not an OME-Zarr image; point "
                         "at the stack's array")
    try:
        return node[image], dict(node.attrs)
    except Exception as exc:  # noqa: BLE001 - a damaged store can fail anywhere
        raise InputError(f"'{path}': its OME-Zarr image '{image}' cannot be read: "
                         f"{one_line(exc)}") from None


def _image_path(group) -> str | None:
    """The full-resolution array of an OME-Zarr image group (NGFF 0.4, or 0.5's ``ome``)."""
    attrs = dict(group.attrs)
    scales = attrs.get("multiscales") or dict(attrs.get("ome") or {}).get("multiscales")
    try:
        return str(scales[0]["datasets"][0]["path"])
    except (TypeError, KeyError, IndexError):
        return None


def settings(path: Path) -> CameraSettings:
    """The settings recorded in the store's ``"emccdcal"`` attribute (unknown names are
    an error, so that a misspelt one is not silently dropped)."""
    arr, group = _open(path)
    recorded = arr.attrs.get(ATTRIBUTE) or group.get(ATTRIBUTE) or {}
    if not isinstance(recorded, dict):
        raise InputError(f"'{path}': its '{ATTRIBUTE}' attribute is not a table of settings")
    recorded = dict(recorded)
    if not recorded and isinstance(group.get("micromanager"), dict):
        from .micromanager import settings_of

        return settings_of(group["micromanager"])
    unknown = sorted(set(recorded) - set(CameraSettings.names()))
    if unknown:
        raise InputError(f"'{path}': unknown camera setting(s) {', '.join(unknown)} in its "
                         f"'{ATTRIBUTE}' attribute (known: {', '.join(CameraSettings.names())})")
    return CameraSettings.from_record(recorded, path)


def header(path: Path):
    """Shape, dtype, and no offset or stride: a store is read by chunks."""
    arr = open_array(path)
    return tuple(arr.shape), arr.dtype, None, None


open_stack = open_array
