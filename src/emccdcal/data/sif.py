"""Andor SIF stacks (iXon cameras, Andor Solis), read through sif-parser (the ``sif`` extra).

sif-parser maps the frames lazily (``np_open(path, lazy="memmap")``): float32 values,
integer counts. Settings it parses: ``GainDAC`` (the EM gain set-point),
``PixelReadoutTime`` (s per pixel), ``DetectorTemperature`` (°C; −999 means not
recorded), ``ExposureTime`` (s), ``DetectorType`` (the model) and ``xbin``/``ybin``;
Andor's pre-amp gain and serial number are not among them.
"""

from __future__ import annotations

from pathlib import Path

from .._util import install_hint, one_line
from ..errors import InputError
from .settings import CameraSettings, recorded_number

__all__ = ["SUFFIXES", "open_sif", "header", "open_stack", "settings"]

#: File name suffixes of this format.
SUFFIXES = (".sif",)


def open_sif(path: Path):
    """The frames (a read-only memory map, (frames, rows, cols)) and the settings."""
    try:
        import sif_parser
    except ImportError:
        raise InputError("reading SIF needs the 'sif' extra: " + install_hint("sif")) from None
    try:
        data, info = sif_parser.np_open(str(path), lazy="memmap")
    except Exception as exc:  # noqa: BLE001 - a damaged file can break the parser anywhere
        raise InputError(
            f"'{path}': not a readable SIF file: {one_line(exc) or type(exc).__name__}"
        ) from None
    return data, _settings(info)


def _number(info, key):
    return recorded_number(info.get(key))


def _settings(info) -> CameraSettings:
    readout, temperature = _number(info, "PixelReadoutTime"), _number(info, "DetectorTemperature")
    exposure = _number(info, "ExposureTime")
    xbin, ybin = info.get("xbin"), info.get("ybin")
    return CameraSettings(
        em_gain_setpoint=_number(info, "GainDAC"),
        readout_rate_mhz=1e-6 / readout if readout else None,
        temperature_c=None if temperature is None or temperature <= -999 else temperature,
        exposure_ms=None if exposure is None else 1000.0 * exposure,
        model=None if info.get("DetectorType") is None else str(info["DetectorType"]),
        binning=None if xbin is None or ybin is None else (int(xbin), int(ybin)),
    )


def header(path: Path):
    """Shape, dtype, and no offset or stride: sif-parser maps the frames itself."""
    arr = open_sif(path)[0]
    return tuple(arr.shape), arr.dtype, None, None


def open_stack(path: Path):
    """The frames, memory-mapped by sif-parser."""
    return open_sif(path)[0]


def settings(path: Path) -> CameraSettings:
    """The camera settings sif-parser reads from the file."""
    return open_sif(path)[1]
