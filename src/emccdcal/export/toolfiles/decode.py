"""DECODE (the ``Camera`` table of its parameter ``.yaml``): writer and the audit's
reader, one plug-in.

DECODE's camera takes one number of each (``baseline`` ADU, ``e_per_adu``, ``em_gain``,
``read_sigma`` e⁻), no per-pixel maps (its per-pixel read-noise class is marked not
ready and reads no file): the medians go there. For a camera without an EM register
``em_gain`` is ``null``, DECODE's sCMOS model (its ``CameraSCMOS``), and the per-pixel
maps go where tools read them (``--to ome-tiff``, ``gdsc``, ``smap``, ``smite``).
"""

from __future__ import annotations

from ... import defaults
from ...errors import InputError
from ...plugins import Tool
from .. import toolkit
from ..toolkit import Field, Reading


def write(cal, s, v, out, qe, pixel_size_nm, name):
    """DECODE ``param.yaml``'s ``Camera`` block (release 0.10 layout)."""
    register = cal.camera_kind not in defaults.WITHOUT_EM_REGISTER
    camera = {
        "baseline": v["offset"]["median"],
        "convert2photons": True,
        "e_per_adu": v["e_per_adu"]["median"],
        "em_gain": v["em_gain"]["median"] if register else None,
        "qe": 1.0 if qe is None else qe,
        "read_sigma": v["read_noise_e"]["median"],
        "spur_noise": 0.0,
    }
    if pixel_size_nm is not None:
        camera["px_size"] = [pixel_size_nm, pixel_size_nm]  # nm, x and y
    text = toolkit.comment_lines(cal, s, v, qe, "# ") + toolkit.yaml_text({"Camera": camera})
    return [toolkit.write_text(out / "decode-camera.yaml", text)]


def _read_doc(doc, path):
    readings = []
    for where, cam in toolkit.find_tables(doc, ("e_per_adu", "em_gain")):
        name = " > ".join(where) or "Camera"
        phi = toolkit.positive(cam["e_per_adu"], f"{name}: e_per_adu", path)
        if cam["em_gain"] is None:
            gain, note = 1.0, "null: DECODE's sCMOS model, no EM gain"
        else:
            gain, note = toolkit.positive(cam["em_gain"], f"{name}: em_gain", path), ""
        fields = [Field("e_per_adu", phi, "e_per_adu"), Field("em_gain", gain, "em_gain", note)]
        baseline = None
        if "baseline" in cam:
            baseline = toolkit.number(cam["baseline"], f"{name}: baseline", path)
            fields.insert(0, Field("baseline", baseline, "offset"))
        if "read_sigma" in cam:
            fields.append(
                Field(
                    "read_sigma",
                    toolkit.number(cam["read_sigma"], "read_sigma", path),
                    "read_noise_e",
                )
            )
        qe = (
            toolkit.quantum_efficiency(cam["qe"], f"{name}: qe", path)
            if cam.get("qe") is not None
            else None
        )
        readings.append(
            Reading("decode", name, tuple(fields), phi / gain, "e_per_adu / em_gain", baseline, qe)
        )
    if not readings:
        raise InputError(
            f"'{path}': no table with e_per_adu and em_gain: not a DECODE camera block"
        )
    return readings


TOOL = Tool(
    "decode",
    "DECODE",
    write,
    lambda path, text, doc, setpoint, tool_gain: _read_doc(doc, path),
    lambda path, text, doc: (
        isinstance(doc, dict)
        and next(toolkit.find_tables(doc, ("e_per_adu", "em_gain")), None) is not None
    ),
)
