"""ThunderSTORM (a Fiji macro's ``Camera setup`` line): writer and the audit's reader,
one plug-in.
"""

from __future__ import annotations

import re

from ...errors import InputError
from ...plugins import Tool
from .. import toolkit
from ..toolkit import Field, Reading


def write(cal, s, v, out, qe, pixel_size_nm, name):
    """An ImageJ macro line of ThunderSTORM's ``Camera setup`` (``photons2adu`` is φ in
    e⁻/ADU, despite its name)."""
    g = v["em_gain"]["median"]
    options = [
        f"offset={toolkit.rounded(v['offset']['median'])!r}",
        f"quantumefficiency={toolkit.rounded(1.0 if qe is None else qe)!r}",
        f"isemgain={'true' if g > 1 else 'false'}",
        f"photons2adu={toolkit.rounded(v['e_per_adu']['median'])!r}",
        f"gainem={toolkit.rounded(g)!r}",
    ]
    if pixel_size_nm is not None:
        options.append(f"pixelsize={toolkit.rounded(pixel_size_nm)!r}")
    text = (
        toolkit.comment_lines(cal, s, v, qe, "// ")
        + f'run("Camera setup", "{" ".join(options)}");\n'
    )
    return [toolkit.write_text(out / "thunderstorm-camera.ijm", text)]


def _read_macro(text, path):
    # comments never run: /* ... */ blocks and // to the end of a line (outside strings)
    code = re.sub(r"/\*.*?\*/", " ", text, flags=re.S)
    code = "\n".join(
        re.sub(r'^((?:[^"/]|"[^"]*"|/(?!/))*)//.*$', r"\1", line) for line in code.splitlines()
    )
    found = re.findall(r'run\(\s*"Camera setup"\s*,\s*"([^"]*)"', code)
    if not found:
        raise InputError(
            f'\'{path}\': no run("Camera setup", "...") line: not a ThunderSTORM camera macro'
        )
    if len(set(found)) > 1:  # each line sets the camera in turn: the last one holds
        raise InputError(
            f"'{path}': {len(found)} different Camera setup lines; the macro's "
            "camera is ambiguous: audit a macro with one"
        )
    options = dict(re.findall(r"(\w+)=(\S+)", found[-1]))
    options = {k.lower(): v for k, v in options.items()}
    missing = [k for k in ("offset", "photons2adu") if k not in options]
    if missing:
        raise InputError(f"'{path}': Camera setup without {', '.join(missing)}")
    phi = toolkit.positive(options["photons2adu"], "photons2adu", path)
    em = options.get("isemgain", "false").lower() == "true"
    gain = toolkit.positive(options.get("gainem", 1), "gainem", path) if em else 1.0
    baseline = toolkit.number(options["offset"], "offset", path)
    fields = (
        Field("offset", baseline, "offset"),
        Field("photons2adu", phi, "e_per_adu", "e-/ADU, despite its name"),
        Field("gainem", gain, "em_gain", "" if em else "isemgain=false: taken as 1"),
    )
    qe = (
        toolkit.quantum_efficiency(options["quantumefficiency"], "quantumefficiency", path)
        if "quantumefficiency" in options
        else None
    )
    return [
        Reading(
            "thunderstorm", "Camera setup", fields, phi / gain, "photons2adu / gainem", baseline, qe
        )
    ]


TOOL = Tool(
    "thunderstorm",
    "ThunderSTORM",
    write,
    lambda path, text, doc, setpoint, tool_gain: _read_macro(text or "", path),
    lambda path, text, doc: text is not None and "Camera setup" in text and "run(" in text,
)
