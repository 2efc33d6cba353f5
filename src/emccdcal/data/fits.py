"""FITS stacks (astronomy EMCCDs; Andor Solis can save FITS), read by sections.

The primary HDU holds the stack, NAXIS3 × NAXIS2 × NAXIS1 = (frames, rows, cols).
Unsigned 16-bit counts are stored as signed integers with BZERO = 32768, which a memory
map cannot undo: frames are read through astropy's ``section``, which reads only the
requested frames and rows. astropy is an optional dependency (the ``fits`` extra).

FITS has no standard camera keywords; those Andor Solis writes are read:
``EXPOSURE`` (s), ``TEMP`` (°C), ``READTIME`` (s per pixel), ``EMREALGN`` or else
``GAIN`` (the EM gain set-point), ``PREAMP``, ``SERNO``, ``HEAD`` (model), ``HBIN`` and
``VBIN``.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from .._util import install_hint
from ..errors import InputError
from .settings import CameraSettings, recorded_number

__all__ = ["SUFFIXES", "FitsStack", "read_header", "header", "open_stack", "settings"]

#: File name suffixes of this format.
SUFFIXES = (".fits", ".fit", ".fts")

# BITPIX (with BZERO for the unsigned types) → the values' dtype once scaled.
_TYPES = {
    (8, 0): "u1",
    (16, 0): "i2",
    (16, 32768): "u2",
    (32, 0): "i4",
    (32, 2**31): "u4",
    (-32, 0): "f4",
    (-64, 0): "f8",
}


def _fits():
    try:
        from astropy.io import fits
    except ImportError:
        raise InputError("reading FITS needs the 'fits' extra: " + install_hint("fits")) from None
    return fits


def read_header(path: Path):
    """Shape, dtype and camera settings of a FITS file's primary HDU, checked against the
    file's size (a truncated file is an error)."""
    fits = _fits()
    try:
        with warnings.catch_warnings():  # a truncation is checked, and said, below
            warnings.simplefilter("ignore")
            with fits.open(path, memmap=False, lazy_load_hdus=True) as hdul:
                hdu = hdul[0]
                header = hdu.header
                info = hdu.fileinfo()
    except (OSError, IndexError) as exc:
        raise InputError(f"'{path}': not a FITS file: {exc}") from None
    naxis = int(header.get("NAXIS", 0))
    if naxis not in (2, 3):
        raise InputError(
            f"'{path}': FITS primary HDU has {naxis} axes; a stack has 3 "
            "(frames, rows, cols) and a map 2"
        )
    shape = tuple(int(header[f"NAXIS{k}"]) for k in range(naxis, 0, -1))
    bitpix, bzero = int(header["BITPIX"]), header.get("BZERO", 0)
    key = (bitpix, int(bzero) if float(bzero).is_integer() else -1)
    if key not in _TYPES or float(header.get("BSCALE", 1)) != 1:
        raise InputError(
            f"'{path}': FITS data of BITPIX {bitpix}, BZERO {bzero}, BSCALE "
            f"{header.get('BSCALE', 1)} are not raw counts"
        )
    dtype = np.dtype(_TYPES[key])
    need = info["datLoc"] + int(np.prod(shape)) * abs(bitpix) // 8
    size = path.stat().st_size
    if need > size:
        raise InputError(
            f"'{path}': truncated: its header describes {' × '.join(map(str, shape))} "
            f"values ending at byte {need}, but the file has {size}"
        )
    return shape, dtype, _settings(header)


def _number(header, key):
    return recorded_number(header.get(key))


def _settings(header) -> CameraSettings:
    exposure, readtime = _number(header, "EXPOSURE"), _number(header, "READTIME")
    gain = _number(header, "EMREALGN")
    gain = _number(header, "GAIN") if gain is None else gain
    hbin, vbin = _number(header, "HBIN"), _number(header, "VBIN")
    preamp, amplifier = header.get("PREAMP"), header.get("OUTPTAMP")
    return CameraSettings(
        em_gain_setpoint=gain,
        analog_gain=None if preamp is None else str(preamp),
        amplifier=None if amplifier is None else str(amplifier).strip(),
        readout_rate_mhz=1e-6 / readtime if readtime else None,
        temperature_c=_number(header, "TEMP"),
        exposure_ms=None if exposure is None else 1000.0 * exposure,
        serial=None if header.get("SERNO") is None else str(header["SERNO"]),
        model=None if header.get("HEAD") is None else str(header["HEAD"]),
        binning=None if hbin is None or vbin is None else (int(hbin), int(vbin)),
    )


class FitsStack:
    """A FITS stack read lazily: indexing reads only the frames and rows asked for.

    Behaves as a read-only array for what the calibration does with a stack: ``shape``,
    ``dtype``, ``ndim``, slicing (``stack[a:b]``, ``stack[:, r0:r1]``) and
    ``np.asarray(stack)``.
    """

    def __init__(self, path: Path):
        self.path = Path(path)
        self.shape, self.dtype, _ = read_header(self.path)
        self.ndim = len(self.shape)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key):
        fits = _fits()
        with fits.open(self.path, memmap=False) as hdul:
            return np.asarray(hdul[0].section[key], dtype=self.dtype)

    def __array__(self, dtype=None, copy=None):
        out = self[(slice(None),) * self.ndim]
        return out if dtype is None else out.astype(dtype)


def header(path: Path):
    """Shape, dtype, and no offset or stride: FITS is read by sections, never mapped."""
    shape, dtype, _ = read_header(path)
    return shape, dtype, None, None


def open_stack(path: Path) -> FitsStack:
    """The stack, read lazily by sections."""
    return FitsStack(path)


def settings(path: Path) -> CameraSettings:
    """The camera settings the header's cards record."""
    return read_header(path)[2]
