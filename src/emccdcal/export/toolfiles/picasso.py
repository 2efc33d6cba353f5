"""Picasso (``config.yaml``'s ``Cameras`` entry): the writer, the multi-mode writer
(``Sensitivity`` nested by read-out mode) and the audit's reader, one plug-in.
"""

from __future__ import annotations

import warnings

from ...errors import ExportWarning, InputError, OptionError
from ...plugins import Tool
from ...result import format_setpoint
from .. import toolkit
from ..toolkit import Field, Reading


def write(cal, s, v, out, qe, pixel_size_nm, name):
    """Picasso's ``config.yaml`` ``Cameras`` entry: what its Localize window loads when
    the camera is chosen (``Baseline`` ADU, ``Sensitivity`` e⁻/ADU, ``DefaultGain``).

    Picasso's window takes the gain as an integer (a ``QSpinBox``), the baseline to 0.1 ADU
    and the sensitivity to 4 decimals. Its photons are (ADU − Baseline)·Sensitivity/Gain,
    so the gain is written rounded and the sensitivity scaled by round(g)/g: their ratio
    stays φ/g (to the 4 decimals), and the file holds exactly what the window shows."""
    g, phi = v["em_gain"]["median"], v["e_per_adu"]["median"]
    gain = max(1, round(g))
    camera = {
        "Baseline": round(v["offset"]["median"], 1),
        "Sensitivity": round(phi * gain / g, 4),
        "DefaultGain": gain,
    }
    if pixel_size_nm is not None:
        camera["Pixelsize"] = pixel_size_nm
    # No "Quantum Efficiency": Picasso keys it by emission wavelength and, since 0.6, does
    # not use it; its photons are photoelectrons (`emccdcal apply --qe` gives photons).
    note = (
        "# Picasso does not use a quantum efficiency: its photons are photoelectrons;\n"
        f"# photons = photoelectrons / {qe:g} (the QE given) are not written here.\n"
        if qe is not None
        else ""
    )
    text = (
        toolkit.comment_lines(cal, s, v, qe, "# ")
        + note
        + f"# Picasso's gain box takes integers: DefaultGain = {gain} for g = {g:.6g}, and\n"
        + f"# Sensitivity = e_per_adu * {gain} / g, so that Sensitivity / Gain = phi / g.\n"
        + "# Merge the Cameras entry into ~/.picasso/config.yaml. For the API, give\n"
        + "# camera_info = {Baseline, Sensitivity, Gain: DefaultGain} to localize().\n"
        + toolkit.yaml_text({"Cameras": {toolkit.camera_name(cal, name): camera}})
    )
    return [toolkit.write_text(out / "picasso-config.yaml", text)]


def write_modes(rows, s, out, pixel_size_nm, name):
    """One Picasso camera whose ``Sensitivity`` is nested by read-out mode (its
    ``Sensitivity Categories``: the Micro-Manager properties that differ between the
    calibrations), so that Picasso picks the mode a movie's metadata names. One
    ``DefaultGain`` serves every mode: each Sensitivity folds in its own mode's true
    gain at the set-point (1 for a mode without multiplication, e.g. the conventional
    amplifier), so Sensitivity / DefaultGain = φ / g in every mode. ``rows``: (calibration,
    set-point used, :func:`camera_values`) per mode."""
    cals = [c for c, _, _ in rows]
    differ = [k for k in toolkit.MODE_FIELDS if len({c.camera.get(k) for c in cals}) > 1]
    for c in cals:
        missing = [k for k in differ if c.camera.get(k) is None]
        if missing:
            raise OptionError(
                f"{c.label}: its files do not record its {', '.join(missing)}; "
                "Picasso's table of read-out modes needs it for every "
                "calibration"
            )
    em_gains = [v["em_gain"]["median"] for _, at, v in rows if at != 1.0]
    gain = max(1, round(em_gains[0])) if em_gains else 1
    sensitivity, lines = {}, []
    for c, at, v in rows:
        g, phi = v["em_gain"]["median"], v["e_per_adu"]["median"]
        node = sensitivity
        keys = [toolkit.mode_key(k, c.camera[k]) for k in differ]
        for key in keys[:-1]:
            node = node.setdefault(key, {})
        if keys[-1] in node:
            raise OptionError(
                f"{c.label}: a second calibration of read-out mode "
                f"{' / '.join(keys)}; give one per mode"
            )
        node[keys[-1]] = round(phi * gain / g, 4)
        lines.append(
            f"{' / '.join(keys)}: e_per_adu {phi:.6g}, em_gain {g:.6g} at "
            f"{format_setpoint(at)}x, baseline {v['offset']['median']:.1f} ADU, "
            f"from {c.label}"
        )
    baselines = [v["offset"]["median"] for _, _, v in rows]
    camera = {
        "Baseline": round(baselines[0], 1),
        "Sensitivity Categories": [toolkit.MODE_FIELDS[k] for k in differ],
        "Sensitivity": sensitivity,
        "DefaultGain": gain,
    }
    if pixel_size_nm is not None:
        camera["Pixelsize"] = pixel_size_nm
    text = "".join(
        f"# {toolkit.comment(line)}\n"
        for line in [
            f"written by emccdcal from {len(cals)} calibrations, one per read-out mode, at EM "
            f"gain set-point {format_setpoint(s)}x (medians over converged pixels):",
            *lines,
            *[
                f"result {r['file']} sha256 {r['sha256']}"
                for c in cals
                for r in c.provenance()["results"]
            ],
        ]
    )
    text += (
        f"# Keep Picasso's gain at DefaultGain = {gain} in every mode: each Sensitivity\n"
        "# is e_per_adu * DefaultGain / em_gain of its mode, so Sensitivity / Gain =\n"
        "# phi / g. The categories are the Micro-Manager properties of Andor's adapter;\n"
        "# rename them to your camera adapter's (Photometrics: Port, ReadoutRate, Gain).\n"
    )
    if max(baselines) - min(baselines) > 1.0:
        text += (
            "# Picasso takes one Baseline per camera; the modes' offsets differ (see\n"
            "# above): set the Baseline of the mode you use.\n"
        )
        warnings.warn(
            f"the read-out modes' offsets differ ({min(baselines):.1f}-"
            f"{max(baselines):.1f} ADU) and Picasso takes one Baseline per camera: "
            f"{baselines[0]:.1f} ADU is written; set the one of the mode you use",
            stacklevel=3,
            category=ExportWarning,
        )
    text += toolkit.yaml_text({"Cameras": {toolkit.camera_name(cals[0], name): camera}})
    return [toolkit.write_text(out / "picasso-config.yaml", text)]


def _picasso_qe(value, name, path):
    """Picasso's QE: a number, or a table by wavelength (each value checked; one value
    is the QE, several leave it to the wavelength the user picks: None)."""
    if value is None:
        return None
    if isinstance(value, dict):
        values = [
            toolkit.quantum_efficiency(v, f"{name}: Quantum Efficiency at {k}", path)
            for k, v in value.items()
        ]
        return values[0] if len(values) == 1 else None
    return toolkit.quantum_efficiency(value, f"{name}: Quantum Efficiency", path)


def read(doc, path, setpoint, tool_gain):
    cameras = doc.get("Cameras") if isinstance(doc, dict) else None
    if not isinstance(cameras, dict) or not cameras:
        raise InputError(f"'{path}': no 'Cameras' table: not a Picasso config.yaml")
    readings = []
    for name, cam in cameras.items():
        if not isinstance(cam, dict) or "Sensitivity" not in cam:
            continue
        gain_key = next((k for k in ("Gain", "DefaultGain") if k in cam), None)
        if tool_gain is not None:
            gain, gain_note = float(tool_gain), "as given (--tool-gain)"
        elif gain_key is not None:
            gain, gain_note = toolkit.positive(cam[gain_key], f"{name}: {gain_key}", path), ""
        else:
            gain, gain_note = (
                float(setpoint),
                ("not in the file: the set-point, as typed into Picasso's EM gain box"),
            )
        baseline = (
            toolkit.number(cam["Baseline"], f"{name}: Baseline", path)
            if "Baseline" in cam
            else None
        )
        qe = _picasso_qe(cam.get("Quantum Efficiency"), name, path)
        for keys, value in toolkit.leaves(cam["Sensitivity"]):
            where = " > ".join(("Cameras", str(name), "Sensitivity", *keys))
            sens = toolkit.positive(value, where, path)
            fields = [
                Field("Sensitivity", sens, "e_per_adu"),
                Field(gain_key or "EM gain", gain, "em_gain", gain_note),
            ]
            if baseline is not None:
                fields.insert(0, Field("Baseline", baseline, "offset"))
            readings.append(
                Reading(
                    "picasso", where, tuple(fields), sens / gain, "Sensitivity / Gain", baseline, qe
                )
            )
    if not readings:
        raise InputError(f"'{path}': no camera of 'Cameras' has a Sensitivity")
    return readings


TOOL = Tool(
    "picasso",
    "Picasso",
    write,
    lambda path, text, doc, setpoint, tool_gain: read(doc, path, setpoint, tool_gain),
    lambda path, text, doc: "Cameras" in (set(doc) if isinstance(doc, dict) else set()),
    write_modes=write_modes,
)
