"""storm-analysis (its analysis ``.xml``): writer and the audit's reader, one plug-in."""

from __future__ import annotations

from ...errors import InputError
from ...plugins import Tool
from .. import toolkit
from ..toolkit import Field, Reading


def write(cal, s, v, out, qe, pixel_size_nm, name):
    """storm-analysis parameters (``camera_gain`` is g/φ in ADU per photoelectron, EM gain
    included; ``camera_offset`` ADU)."""
    comment = toolkit.comment_lines(cal, s, v, qe, "  ").replace("--", "- -")
    text = (
        '<?xml version="1.0" encoding="utf-8"?>\n<!--\n' + comment + "-->\n<settings>\n"
        f'  <camera_gain type="float">{toolkit.rounded(v["adu_per_e_total"]["median"])!r}'
        "</camera_gain>\n"
        f'  <camera_offset type="float">{toolkit.rounded(v["offset"]["median"])!r}'
        "</camera_offset>\n"
    )
    if pixel_size_nm is not None:
        text += f'  <pixel_size type="float">{toolkit.rounded(pixel_size_nm)!r}</pixel_size>\n'
    text += "</settings>\n"
    return [toolkit.write_text(out / "storm-analysis.xml", text)]


def _read_xml(path):
    root = toolkit.load_xml(path, what="storm-analysis parameters file")
    values = {el.tag: el.text for el in root.iter() if el.tag in ("camera_gain", "camera_offset")}
    if "camera_gain" not in values:
        raise InputError(f"'{path}': no camera_gain: not storm-analysis parameters")
    gain = toolkit.positive(values["camera_gain"], "camera_gain", path)
    fields = [Field("camera_gain", gain, "adu_per_e_total", "g/phi, ADU per photoelectron")]
    baseline = None
    if "camera_offset" in values:
        baseline = toolkit.number(values["camera_offset"], "camera_offset", path)
        fields.insert(0, Field("camera_offset", baseline, "offset"))
    return [
        Reading("storm-analysis", "settings", tuple(fields), 1 / gain, "1 / camera_gain", baseline)
    ]


TOOL = Tool(
    "storm-analysis",
    "storm-analysis",
    write,
    lambda path, text, doc, setpoint, tool_gain: _read_xml(path),
    lambda path, text, doc: path.suffix.lower() == ".xml",
)
