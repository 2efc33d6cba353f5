"""Andor SIF stacks (iXon cameras, Andor Solis), read through sif-parser (the ``sif`` extra).

sif-parser maps the frames lazily (``np_open(path, lazy="memmap")``): float32 values,
integer counts. Settings it parses: ``GainDAC`` (the EM gain set-point),
``PixelReadoutTime`` (s per pixel), ``DetectorTemperature`` (°C; −999 means not
recorded), ``ExposureTime`` (s), ``DetectorType`` (the model) and ``xbin``/``ybin``;
Andor's pre-amp gain and serial number are not among them.

The model says the kind of camera (:func:`camera_kind`): an iXon (``DU897``, ``DU888`` …)
is an EMCCD, an iDus (``DU420`` …) a CCD without an EM register and an iStar (``DH734``
…) an intensified CCD; for the last two ``GainDAC`` is not an EM gain set-point (an
iStar's is its intensifier's gain) and is not recorded as one.
"""

from __future__ import annotations

from pathlib import Path

from .._util import install_hint, one_line
from ..errors import InputError
from .settings import CameraSettings, kind_of_model, recorded_number

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


def camera_kind(model) -> str | None:
    """The kind of an Andor camera from its model (``DetectorType``), where the model
    says it: iXon ``emccd``, iDus ``ccd``, iStar (``DH…``) ``iccd``, Zyla/Sona/Neo/Marana
    ``scmos``; else None (:func:`emccdcal.data.settings.kind_of_model`).

    >>> camera_kind("DU897_BV"), camera_kind("DU420A_BEX2-DD"), camera_kind("DH734_18F")
    ('emccd', 'ccd', 'iccd')
    """
    return kind_of_model(model)


def _settings(info) -> CameraSettings:
    readout, temperature = _number(info, "PixelReadoutTime"), _number(info, "DetectorTemperature")
    exposure = _number(info, "ExposureTime")
    xbin, ybin = info.get("xbin"), info.get("ybin")
    model = None if info.get("DetectorType") is None else str(info["DetectorType"])
    kind = camera_kind(model)
    return CameraSettings(
        em_gain_setpoint=_number(info, "GainDAC") if kind in (None, "emccd") else None,
        camera_kind=kind,
        readout_rate_mhz=1e-6 / readout if readout else None,
        temperature_c=None if temperature is None or temperature <= -999 else temperature,
        exposure_ms=None if exposure is None else 1000.0 * exposure,
        model=model,
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
