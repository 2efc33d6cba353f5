"""smite (LidkeLab's MATLAB SMLM toolbox): its camera calibration file, writer and the
audit's reader, one plug-in.

smite reads a calibration file with ``load(path, 'Params')`` and takes ``Params.Gain``
(ADU per photoelectron), ``Params.CCDOffset`` (ADU) and ``Params.CCDVar`` (ADU², which
its code calls the read noise) per pixel, and ``Params.CameraObj.ROI``, the sensor region
in 1-based inclusive pixels as ``[YStart, XStart, YEnd, XEnd]``; an ROI whose second and
fourth values exceed its first and third is taken as the older ``[YStart, YEnd, XStart,
XEnd]`` and reordered (smite's ``loadDataCalibration``), so the writer picks the order
that reader reads back as the region meant.
"""

from __future__ import annotations

import json

import numpy as np

from ...errors import InputError
from ...model import adc
from ...plugins import Tool
from .. import toolkit

#: The file written.
FILE = "smite-calibration.mat"


def roi_of(origin, shape) -> list[int]:
    """smite's ``CameraObj.ROI`` of the region at ``origin`` (row, col, 0-based) of
    ``shape``: ``[YStart, XStart, YEnd, XEnd]`` (1-based, inclusive), or the older
    ``[YStart, YEnd, XStart, XEnd]`` where smite would take the newer one for it.

    >>> roi_of((0, 0), (8, 8)), roi_of((0, 10), (8, 8))
    ([1, 1, 8, 8], [1, 8, 11, 18])
    """
    (r0, c0), (rows, cols) = origin, shape
    y0, x0, y1, x1 = r0 + 1, c0 + 1, r0 + rows, c0 + cols
    if x0 > y0 and x1 > y1:  # smite would reorder [y0, x0, y1, x1]: give it the old order
        return [y0, y1, x0, x1]
    return [y0, x0, y1, x1]


def origin_of(roi) -> tuple[int, int]:
    """The 0-based (row, col) of an ROI as smite reads it (its reordering included)."""
    roi = [int(round(float(v))) for v in np.ravel(roi)]
    if len(roi) != 4:
        raise InputError(f"CameraObj.ROI has {len(roi)} values, not 4")
    if roi[1] > roi[0] and roi[3] > roi[2]:  # the older order
        roi = [roi[0], roi[2], roi[1], roi[3]]
    return roi[0] - 1, roi[1] - 1


def write(cal, s, v, out, qe, pixel_size_nm, name):
    """smite's calibration file: per pixel ``Gain`` = g/φ (ADU/e⁻; also ``CCDGain``),
    ``CCDOffset`` (ADU) and ``CCDVar`` (the read-out variance as the dark counts show it,
    ADU²), float32, [row, col], and the region (``CameraObj.ROI``)."""
    from scipy.io import savemat

    offset, sigma = cal.dark(s)
    gain = (cal.gain(s) / cal.e_per_adu).astype(np.float32)
    origin = cal.origin if cal.origin is not None else (0, 0)
    params = {
        "Gain": gain,
        "CCDGain": gain,
        "CCDOffset": offset.astype(np.float32),
        "CCDVar": adc.count_variance(sigma, s == 1).astype(np.float32),
        "CameraObj": {"ROI": np.array(roi_of(origin, offset.shape), dtype=float)},
        "emccdcal": json.dumps(toolkit.provenance(cal, s, qe)),
    }
    path = out / FILE
    toolkit.write_file(path, lambda p: savemat(p, {"Params": params}))
    return [path]


def read(path, setpoint):
    """The audit's reading of a smite calibration file (None: not one)."""
    if path.suffix.lower() != ".mat":
        return None
    raw = toolkit.mat_raw(path, squeeze=True)
    params = raw.get("Params")
    if params is None or not all(hasattr(params, k) for k in ("Gain", "CCDOffset", "CCDVar")):
        return None
    maps = {
        "offset": np.asarray(params.CCDOffset, dtype=float),
        "adu_per_e_total": np.asarray(params.Gain, dtype=float),
        "variance": np.asarray(params.CCDVar, dtype=float),
    }
    camera = getattr(params, "CameraObj", None)
    try:
        origin = None if camera is None else origin_of(camera.ROI)
    except (AttributeError, InputError) as exc:
        raise InputError(f"'{path}': {exc}") from None
    return toolkit.per_pixel_reading(
        "smite", "Params", path, maps, origin, names=("CCDOffset", "Gain"),
        gain_note="ADU per photoelectron",
    )  # fmt: skip


TOOL = Tool(
    "smite",
    "smite",
    write,
    None,
    None,
    read_file=read,
)
