"""gdsc-smlm (its ``intensityCalibration`` JSON): writer and the audit's reader, one
plug-in.
"""

from __future__ import annotations

import json

from ...errors import InputError
from ...plugins import Tool
from .. import toolkit
from ..toolkit import Field, Reading


def write(cal, s, v, out, qe, pixel_size_nm, name):
    """gdsc-smlm's ``Calibration`` message as protobuf JSON (``count_per_photon`` is the
    total gain QE·g/φ in counts per photon; ``read_noise`` and ``bias`` in counts)."""
    q = 1.0 if qe is None else qe
    prov = toolkit.provenance(cal, s, qe)
    sha = ",".join(r["sha256"][:12] for r in prov["results"])
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
    return [toolkit.write_text(out / "gdsc-calibration.json", json.dumps(message, indent=2) + "\n")]


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
)
