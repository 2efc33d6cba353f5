"""PYME (the camera's metadata as JSON or ``.md``, and its per-pixel maps): writer and
the audit's reader, one plug-in.
"""

from __future__ import annotations

import json
import re

import numpy as np

from ...errors import InputError
from ...plugins import Tool
from .. import toolkit
from ..toolkit import Field, Reading


def write(cal, s, v, out, qe, pixel_size_nm, name):
    """PYME metadata (flat dotted keys) with its dark, variance and flat-field maps."""
    offset, sigma = cal.dark(s)
    phi, gain = cal.e_per_adu, cal.gain(s)
    total = v["adu_per_e_total"]["median"]
    flat = (phi / gain) * total  # PYME multiplies (counts − dark) by it: ≈ 1, per pixel
    prov = toolkit.provenance(cal, s, qe)
    maps = {
        "dark": (offset, "ADU"),
        "variance": ((sigma * phi) ** 2, "e-^2"),
        "flatfield": (flat, "1"),
    }
    files = {}
    for key, (image, unit) in maps.items():
        image = np.where(np.isfinite(image), image, np.nanmedian(image))  # PYME needs every pixel
        files[key] = toolkit.write_tiff(
            out / f"pyme-{key}.tif", image, {"quantity": f"PYME {key} map", "units": unit, **prov}
        )
    md = {
        "Camera.ADOffset": v["offset"]["median"],
        "Camera.ElectronsPerCount": v["e_per_adu"]["median"],
        "Camera.TrueEMGain": v["em_gain"]["median"],
        "Camera.ReadNoise": v["read_noise_e"]["median"],
        "Camera.NoiseFactor": 1.41 if v["em_gain"]["median"] > 1 else 1.0,
        # names beside pyme.json, never this machine's absolute paths: the folder moves
        "Camera.DarkMapID": files["dark"].name,
        "Camera.VarianceMapID": files["variance"].name,
        "Camera.FlatfieldMapID": files["flatfield"].name,
    }
    if qe is not None:
        md["Camera.QuantumEfficiency"] = qe
    if pixel_size_nm is not None:
        md["voxelsize.x"] = md["voxelsize.y"] = pixel_size_nm / 1000.0  # µm
    md = {k: (toolkit.rounded(x) if isinstance(x, float) else x) for k, x in md.items()}
    md["emccdcal.Provenance"] = json.dumps(prov)
    text = json.dumps(md, indent=2, sort_keys=True) + "\n"
    return [toolkit.write_text(out / "pyme.json", text), *files.values()]


def _read_doc(doc, path):
    flat = {}
    for keys, value in toolkit.leaves(doc):
        flat[".".join(keys)] = value
    if "Camera.ElectronsPerCount" not in flat:
        raise InputError(f"'{path}': no Camera.ElectronsPerCount: not PYME metadata")
    phi = toolkit.positive(flat["Camera.ElectronsPerCount"], "Camera.ElectronsPerCount", path)
    gain = toolkit.positive(flat.get("Camera.TrueEMGain", 1.0), "Camera.TrueEMGain", path)
    fields = [
        Field("Camera.ElectronsPerCount", phi, "e_per_adu"),
        Field("Camera.TrueEMGain", gain, "em_gain"),
    ]
    baseline = None
    if "Camera.ADOffset" in flat:
        baseline = toolkit.number(flat["Camera.ADOffset"], "Camera.ADOffset", path)
        fields.insert(0, Field("Camera.ADOffset", baseline, "offset"))
    if "Camera.ReadNoise" in flat:
        fields.append(
            Field(
                "Camera.ReadNoise",
                toolkit.number(flat["Camera.ReadNoise"], "Camera.ReadNoise", path),
                "read_noise_e",
            )
        )
    return [
        Reading(
            "pyme",
            "metadata",
            tuple(fields),
            phi / gain,
            "ElectronsPerCount / TrueEMGain",
            baseline,
        )
    ]


def _pyme_md(text):
    """PYME's ``.md`` metadata (Python assignments) as a dict: numbers only, never run."""
    found = {}
    for key, value in re.findall(
        r"""^\s*md\[\s*['"]([\w.]+)['"]\s*\]\s*=\s*(.*?)\s*(?:#.*)?$""", text, flags=re.M
    ):
        if not re.fullmatch(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?", value):
            value = f"{value} (an expression, never evaluated)"  # refused as not a number
        found[key] = value
    return found


TOOL = Tool(
    "pyme",
    "PYME",
    write,
    lambda path, text, doc, setpoint, tool_gain: _read_doc(
        doc if isinstance(doc, dict) and doc else _pyme_md(text or ""), path
    ),
    lambda path, text, doc: (
        path.suffix.lower() == ".md"
        or (
            isinstance(doc, dict)
            and "Camera.ElectronsPerCount" in {".".join(k) for k, _ in toolkit.leaves(doc)}
        )
    ),
)
