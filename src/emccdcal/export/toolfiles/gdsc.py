"""gdsc-smlm (its ``intensityCalibration`` JSON, and for a camera without an EM register
its per-pixel camera model): writer and the audit's readers, one plug-in.

gdsc-smlm's per-pixel camera model (its Camera Model Manager) is a float32 ImageJ TIFF of
three slices, ``Bias`` (counts), ``Gain`` (counts per photon) and ``Variance`` (counts²),
whose ImageJ calibration's x and y origin place it on the sensor; the calibration JSON
names it (``cameraModelName``, the file's name without its extension) with
``cameraType`` ``SCMOS``.
"""

from __future__ import annotations

import json

import numpy as np

from ... import defaults
from ...errors import InputError
from ...model import adc
from ...plugins import Tool
from .. import toolkit
from ..toolkit import Field, Reading


#: The per-pixel camera model's file (its name is the model's name in gdsc-smlm).
MODEL_FILE = "gdsc-camera-model.tif"
_INFO = "Per-pixel camera model data"


def write(cal, s, v, out, qe, pixel_size_nm, name):
    """gdsc-smlm's ``Calibration`` message as protobuf JSON (``count_per_photon`` is the
    total gain QE·g/φ in counts per photon; ``read_noise`` and ``bias`` in counts), and
    for a camera without an EM register its per-pixel camera model (:data:`MODEL_FILE`)."""
    q = 1.0 if qe is None else qe
    prov = toolkit.provenance(cal, s, qe)
    sha = ",".join(r["sha256"][:12] for r in prov["results"])
    per_pixel = cal.camera_kind in defaults.WITHOUT_EM_REGISTER
    message = {
        "intensityCalibration": {
            "intensityUnit": "COUNT",
            "countPerPhoton": toolkit.rounded(q * v["adu_per_e_total"]["median"]),
        },
        "cameraCalibration": {
            "cameraType": "EMCCD",
            "readNoise": toolkit.rounded(v["read_noise"]["median"]),
            "bias": toolkit.rounded(v["offset"]["median"]),
            "quantumEfficiency": toolkit.rounded(q),
            # the one free-text field: the provenance (EMCCDs use no model)
            "cameraModelName": f"emccdcal {prov['emccdcal_version']} {prov['method']} sha256 {sha}",
        },
    }
    if pixel_size_nm is not None:
        message["distanceCalibration"] = {
            "distanceUnit": "PIXEL",
            "nmPerPixel": toolkit.rounded(pixel_size_nm),
        }
    written = []
    if per_pixel:
        camera = message["cameraCalibration"]
        camera["cameraType"] = "SCMOS"
        camera["cameraModelName"] = MODEL_FILE.removesuffix(".tif")
        written.append(_write_model(cal, s, q, out / MODEL_FILE, prov))
    path = toolkit.write_text(out / "gdsc-calibration.json", json.dumps(message, indent=2) + "\n")
    return [path, *written]


def _write_model(cal, s, q, path, prov):
    """The per-pixel camera model: Bias (ADU), Gain (QE·g/φ, counts per photon) and
    Variance (the read-out's, as the dark counts show it: σ² + 1/12 where σ is the analog
    read noise), float32, with the sensor origin as ImageJ's x/y origin."""
    import tifffile

    offset, sigma = cal.dark(s)
    slices = np.stack(
        [offset, q * cal.gain(s) / cal.e_per_adu, adc.count_variance(sigma, s == 1)]
    ).astype(np.float32)
    row, col = cal.origin if cal.origin is not None else (0, 0)
    metadata = {
        "axes": "ZYX",  # three slices of one stack, as gdsc-smlm reads them
        "Labels": ["Bias", "Gain", "Variance"],
        "Info": _INFO + "\nemccdcal " + json.dumps(prov),
        "xorigin": col,
        "yorigin": row,
    }
    return toolkit.write_file(
        path, lambda p: tifffile.imwrite(p, slices, imagej=True, metadata=metadata)
    )


def read_model(path, setpoint):
    """The audit's reading of a per-pixel camera model TIFF (None: not one)."""
    import tifffile

    if path.suffix.lower() not in (".tif", ".tiff"):
        return None
    with tifffile.TiffFile(path) as tif:
        meta = tif.imagej_metadata or {}
        if not str(meta.get("Info", "")).startswith(_INFO):
            return None
        data = tif.asarray()
    if data.ndim != 3 or data.shape[0] != 3:
        raise InputError(
            f"'{path}': a camera model has 3 slices (Bias, Gain, Variance); got {data.shape}"
        )
    bias, gain, variance = (np.asarray(a, dtype=float) for a in data)
    origin = (int(round(float(meta.get("yorigin", 0)))), int(round(float(meta.get("xorigin", 0)))))
    maps = {"offset": bias, "adu_per_e_total": gain, "variance": variance}
    return toolkit.per_pixel_reading(
        "gdsc", "per-pixel camera model", path, maps, origin, names=("Bias", "Gain slice"),
        gain_note="counts per photon",
    )  # fmt: skip


def _read_doc(doc, path):
    def get(table, *names):
        for n in names:
            if isinstance(table, dict) and n in table:
                return table[n]
        return None

    intensity = get(doc, "intensityCalibration", "intensity_calibration")
    camera = get(doc, "cameraCalibration", "camera_calibration") or {}
    cpp = get(intensity, "countPerPhoton", "count_per_photon")
    if cpp is None:
        raise InputError(f"'{path}': no countPerPhoton: not a gdsc-smlm Calibration")
    cpp = toolkit.positive(cpp, "countPerPhoton", path)
    qe = get(camera, "quantumEfficiency", "quantum_efficiency")
    qe = 1.0 if qe is None else toolkit.quantum_efficiency(qe, "quantumEfficiency", path)
    fields = [
        Field(
            "countPerPhoton", cpp / qe, "adu_per_e_total", f"QE x g/phi; divided by its QE {qe:g}"
        )
    ]
    baseline = get(camera, "bias")
    if baseline is not None:
        baseline = toolkit.number(baseline, "bias", path)
        fields.insert(0, Field("bias", baseline, "offset"))
    noise = get(camera, "readNoise", "read_noise")
    if noise is not None:
        fields.append(Field("readNoise", toolkit.number(noise, "readNoise", path), "read_noise"))
    return [
        Reading("gdsc", "Calibration", tuple(fields), qe / cpp, "QE / countPerPhoton", baseline, qe)
    ]


TOOL = Tool(
    "gdsc",
    "gdsc-smlm",
    write,
    lambda path, text, doc, setpoint, tool_gain: _read_doc(doc, path),
    lambda path, text, doc: bool(
        (set(doc) if isinstance(doc, dict) else set())
        & {"intensityCalibration", "intensity_calibration"}
    ),
    read_file=read_model,
)
