"""``emccdcal export``: a calibration in each localization tool's own file, names and units.

Every tool names the same few numbers differently, and three of the names mislead:
ThunderSTORM's ``photons2ADU`` is φ in e⁻/ADU; gdsc-smlm's ``count_per_photon`` is the
total gain QE·g/φ; storm-analysis's ``camera_gain`` is g/φ in ADU per e⁻. Here each is
written once, from the formulas in the table of ``docs/exports.md``, which gives every
tool's file, field, our quantity, unit and formula, with where in the tool's source each
name is read.

A tool that takes one number gets the median over the converged pixels; the files that
allow it also record the pixels' robust spread (1.4826 × MAD) and how many pixels there
were. Per-pixel maps go where a tool reads them (PYME's dark, variance and flat-field
maps; the ``fits`` and ``tiff-maps`` targets). Every file records its provenance: the
emccdcal version, the method, the result files and their SHA-256.

Examples
--------
>>> from emccdcal.export.tools import TOOLS
>>> [t for t in ("picasso", "thunderstorm", "json") if t in TOOLS]
['picasso', 'thunderstorm', 'json']
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np

from .. import plugins
from .._output import atomic_write, comment
from .._output import atomic_write_text as _write_text
from ..errors import OptionError
from ..result import Calibration, format_setpoint, load_calibration, pixel_statistics

__all__ = ["TOOLS", "export", "export_modes", "camera_values", "readout_mode", "MODE_FIELDS"]


def __getattr__(name):
    if name == "TOOLS":  # the ``--to`` targets: every tool registered (emccdcal.plugins)
        return tuple(plugins.load(plugins.TOOLS))
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# --------------------------------------------------------------------------------------
# The numbers every tool is made of
# --------------------------------------------------------------------------------------
def pick_setpoint(cal: Calibration, setpoint=None) -> float:
    """The set-point an export is for: the one given, or the only multiplied one.

    Raises
    ------
    OptionError
        None given and the calibration has several multiplied set-points, or the one
        given is not in it.
    """
    if setpoint is not None:
        cal.gain(setpoint)  # raises, naming what the calibration has
        return float(setpoint)
    multiplied = [s for s in cal.setpoints if s != 1.0]
    if len(multiplied) > 1:
        have = ", ".join(format_setpoint(s) + "x" for s in cal.setpoints)
        raise OptionError(f"{cal.label}: has set-points {have}; a tool takes the gain of one: "
                          "give --setpoint G (the set-point the movies were recorded at)")
    return multiplied[0] if multiplied else 1.0


def camera_values(cal: Calibration, setpoint: float) -> dict:
    """Median over converged pixels (with spread and count) of what the tools take, at one
    set-point.

    Returns
    -------
    dict
        ``e_per_adu`` (e⁻/ADU), ``em_gain`` (1), ``adu_per_e_total`` = g/φ (ADU per
        photoelectron, EM gain included), ``offset`` and ``read_noise`` (ADU),
        ``read_noise_e`` = σ·φ (e⁻): each ``{"median", "spread", "n"}``.
    """
    phi, gain = cal.e_per_adu, cal.gain(setpoint)
    offset, sigma = cal.dark(setpoint)
    values = {"e_per_adu": phi, "em_gain": gain, "adu_per_e_total": gain / phi,
              "offset": offset, "read_noise": sigma, "read_noise_e": sigma * phi}
    out = {k: pixel_statistics(v) for k, v in values.items()}
    for name, stats in out.items():
        if stats["median"] is None or not math.isfinite(stats["median"]):
            raise OptionError(f"{cal.label}: no converged pixel has a finite {name} at "
                              f"set-point {format_setpoint(setpoint)}x")
    return out


#: The camera settings that make a read-out mode, with the Micro-Manager property names
#: of Andor's adapter, which Picasso matches its ``Sensitivity Categories`` against.
MODE_FIELDS = {"amplifier": "Output_Amplifier", "readout_rate_mhz": "ReadoutMode",
               "analog_gain": "Pre-Amp-Gain"}


def readout_mode(cal: Calibration) -> tuple:
    """The calibration's read-out mode as its files recorded it: ``(amplifier, read-out
    rate in MHz, analog gain)``, ``None`` where not recorded."""
    return tuple(cal.camera.get(k) for k in MODE_FIELDS)


def _mode_key(field_name, value) -> str:
    """A mode's value as Micro-Manager's Andor adapter writes it ("17.000 MHz")."""
    return f"{float(value):.3f} MHz" if field_name == "readout_rate_mhz" else str(value)


def _provenance(cal: Calibration, setpoint=None, qe=None) -> dict:
    doc = cal.provenance()
    if setpoint is not None:
        doc["setpoint"] = setpoint
    if qe is not None:
        doc["quantum_efficiency_given"] = qe
    return doc


def _comment_lines(cal, setpoint, values, qe, prefix) -> str:
    """Provenance and the pixels' spread, as comment lines of a text format."""
    p = _provenance(cal, setpoint, qe)
    lines = [f"written by emccdcal {p['emccdcal_version']} from {p['method']} "
             f"({p['em_model']} register), calibration of {p['created']}",
             f"at EM gain set-point {format_setpoint(setpoint)}x; medians over "
             f"{values['e_per_adu']['n']} converged pixels (robust spread in brackets):"]
    for name, unit in (("e_per_adu", "e-/ADU"), ("em_gain", ""), ("offset", "ADU"),
                       ("read_noise", "ADU")):
        v = values[name]
        spread = "n/a" if v["spread"] is None else f"{v['spread']:.4g}"
        lines.append(f"  {name} = {v['median']:.6g} {unit} ({spread})")
    lines += [f"result {r['file']} sha256 {r['sha256']}" for r in p["results"]]
    if setpoint in cal.predicted:
        g = cal.predicted[setpoint]
        lines.append(f"the gain at {format_setpoint(setpoint)}x was not measured: "
                     f"{g['gain']:.6g} +/- {g['se_of_median']:.2g} (se_of_median) predicted by "
                     f"the gain curve {g['curve']}; extrapolated = "
                     f"{str(g['extrapolated']).lower()}")
    return "".join(f"{prefix}{comment(line)}\n" for line in lines)  # paths are data


def _number(x) -> float:
    return float(f"{float(x):.7g}")  # seven digits: far below any calibration's error


# --------------------------------------------------------------------------------------
# Small writers
# --------------------------------------------------------------------------------------
def _yaml(doc: dict, indent: int = 0) -> str:
    """A nested dict of scalars (and lists of them) as block YAML; string keys and values
    double-quoted, as JSON strings are valid YAML.

    >>> print(_yaml({"Camera": {"baseline": 100.0, "px_size": [100, 100]}}), end="")
    "Camera":
      "baseline": 100.0
      "px_size": [100, 100]
    """
    out = []
    for key, value in doc.items():
        k = json.dumps(key) if isinstance(key, str) else str(key)
        if isinstance(value, dict):
            out.append(f"{' ' * indent}{k}:\n{_yaml(value, indent + 2)}")
        elif isinstance(value, list):
            out.append(f"{' ' * indent}{k}: [{', '.join(map(_scalar, value))}]\n")
        else:
            out.append(f"{' ' * indent}{k}: {_scalar(value)}\n")
    return "".join(out)


def _scalar(value) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float, np.number)):
        return repr(_number(value)) if isinstance(value, (float, np.floating)) else str(value)
    return json.dumps(str(value))


def _write_tiff(path: Path, image, description: dict) -> Path:
    import tifffile

    data = np.asarray(image, dtype=np.float32)
    return atomic_write(path, lambda p: tifffile.imwrite(
        p, data, description=json.dumps(description), metadata=None))


def _camera_name(cal: Calibration, name) -> str:
    if name:
        return str(name)
    parts = [cal.camera.get("model"), cal.camera.get("serial")]
    return " ".join(str(p) for p in parts if p) or "EMCCD (emccdcal)"


# --------------------------------------------------------------------------------------
# One function per tool: (cal, setpoint, values, out, options) -> files written
# --------------------------------------------------------------------------------------
def _picasso(cal, s, v, out, qe, pixel_size_nm, name):
    """Picasso's ``config.yaml`` ``Cameras`` entry: what its Localize window loads when
    the camera is chosen (``Baseline`` ADU, ``Sensitivity`` e⁻/ADU, ``DefaultGain``).

    Picasso's window takes the gain as an integer (a ``QSpinBox``), the baseline to 0.1 ADU
    and the sensitivity to 4 decimals. Its photons are (ADU − Baseline)·Sensitivity/Gain,
    so the gain is written rounded and the sensitivity scaled by round(g)/g: their ratio
    stays φ/g (to the 4 decimals), and the file holds exactly what the window shows."""
    g, phi = v["em_gain"]["median"], v["e_per_adu"]["median"]
    gain = max(1, round(g))
    camera = {"Baseline": round(v["offset"]["median"], 1),
              "Sensitivity": round(phi * gain / g, 4), "DefaultGain": gain}
    if pixel_size_nm is not None:
        camera["Pixelsize"] = pixel_size_nm
    # No "Quantum Efficiency": Picasso keys it by emission wavelength and, since 0.6, does
    # not use it; its photons are photoelectrons (`emccdcal apply --qe` gives photons).
    note = ("# Picasso does not use a quantum efficiency: its photons are photoelectrons;\n"
            f"# photons = photoelectrons / {qe:g} (the QE given) are not written here.\n"
            if qe is not None else "")
    text = (_comment_lines(cal, s, v, qe, "# ") + note
            + f"# Picasso's gain box takes integers: DefaultGain = {gain} for g = {g:.6g}, and\n"
            + f"# Sensitivity = e_per_adu * {gain} / g, so that Sensitivity / Gain = phi / g.\n"
            + "# Merge the Cameras entry into ~/.picasso/config.yaml. For the API, give\n"
            + "# camera_info = {Baseline, Sensitivity, Gain: DefaultGain} to localize().\n"
            + _yaml({"Cameras": {_camera_name(cal, name): camera}}))
    return [_write_text(out / "picasso-config.yaml", text)]


def _picasso_modes(rows, s, out, pixel_size_nm, name):
    """One Picasso camera whose ``Sensitivity`` is nested by read-out mode (its
    ``Sensitivity Categories``: the Micro-Manager properties that differ between the
    calibrations), so that Picasso picks the mode a movie's metadata names. One
    ``DefaultGain`` serves every mode: each Sensitivity folds in its own mode's true
    gain at the set-point (1 for a mode without multiplication, e.g. the conventional
    amplifier), so Sensitivity / DefaultGain = φ / g in every mode. ``rows``: (calibration,
    set-point used, :func:`camera_values`) per mode."""
    cals = [c for c, _, _ in rows]
    differ = [k for k in MODE_FIELDS if len({c.camera.get(k) for c in cals}) > 1]
    for c in cals:
        missing = [k for k in differ if c.camera.get(k) is None]
        if missing:
            raise OptionError(f"{c.label}: its files do not record its {', '.join(missing)}; "
                              "Picasso's table of read-out modes needs it for every "
                              "calibration")
    em_gains = [v["em_gain"]["median"] for _, at, v in rows if at != 1.0]
    gain = max(1, round(em_gains[0])) if em_gains else 1
    sensitivity, lines = {}, []
    for c, at, v in rows:
        g, phi = v["em_gain"]["median"], v["e_per_adu"]["median"]
        node = sensitivity
        keys = [_mode_key(k, c.camera[k]) for k in differ]
        for key in keys[:-1]:
            node = node.setdefault(key, {})
        if keys[-1] in node:
            raise OptionError(f"{c.label}: a second calibration of read-out mode "
                              f"{' / '.join(keys)}; give one per mode")
        node[keys[-1]] = round(phi * gain / g, 4)
        lines.append(f"{' / '.join(keys)}: e_per_adu {phi:.6g}, em_gain {g:.6g} at "
                     f"{format_setpoint(at)}x, baseline {v['offset']['median']:.1f} ADU, "
                     f"from {c.label}")
    baselines = [v["offset"]["median"] for _, _, v in rows]
    camera = {"Baseline": round(baselines[0], 1), "Sensitivity Categories":
              [MODE_FIELDS[k] for k in differ], "Sensitivity": sensitivity,
              "DefaultGain": gain}
    if pixel_size_nm is not None:
        camera["Pixelsize"] = pixel_size_nm
    text = "".join(f"# {comment(line)}\n" for line in [
        f"written by emccdcal from {len(cals)} calibrations, one per read-out mode, at EM "
        f"gain set-point {format_setpoint(s)}x (medians over converged pixels):", *lines,
        *[f"result {r['file']} sha256 {r['sha256']}" for c in cals
          for r in c.provenance()["results"]]])
    text += (f"# Keep Picasso's gain at DefaultGain = {gain} in every mode: each Sensitivity\n"
             "# is e_per_adu * DefaultGain / em_gain of its mode, so Sensitivity / Gain =\n"
             "# phi / g. The categories are the Micro-Manager properties of Andor's adapter;\n"
             "# rename them to your camera adapter's (Photometrics: Port, ReadoutRate, Gain).\n")
    if max(baselines) - min(baselines) > 1.0:
        text += ("# Picasso takes one Baseline per camera; the modes' offsets differ (see\n"
                 "# above): set the Baseline of the mode you use.\n")
        warnings.warn(f"the read-out modes' offsets differ ({min(baselines):.1f}-"
                      f"{max(baselines):.1f} ADU) and Picasso takes one Baseline per camera: "
                      f"{baselines[0]:.1f} ADU is written; set the one of the mode you use",
                      stacklevel=3)
    text += _yaml({"Cameras": {_camera_name(cals[0], name): camera}})
    return [_write_text(out / "picasso-config.yaml", text)]


def _pyme(cal, s, v, out, qe, pixel_size_nm, name):
    """PYME metadata (flat dotted keys) with its dark, variance and flat-field maps."""
    offset, sigma = cal.dark(s)
    phi, gain = cal.e_per_adu, cal.gain(s)
    total = v["adu_per_e_total"]["median"]
    flat = (phi / gain) * total  # PYME multiplies (counts − dark) by it: ≈ 1, per pixel
    prov = _provenance(cal, s, qe)
    maps = {"dark": (offset, "ADU"), "variance": ((sigma * phi) ** 2, "e-^2"),
            "flatfield": (flat, "1")}
    files = {}
    for key, (image, unit) in maps.items():
        image = np.where(np.isfinite(image), image, np.nanmedian(image))  # PYME needs every pixel
        files[key] = _write_tiff(out / f"pyme-{key}.tif", image,
                                 {"quantity": f"PYME {key} map", "units": unit, **prov})
    md = {"Camera.ADOffset": v["offset"]["median"],
          "Camera.ElectronsPerCount": v["e_per_adu"]["median"],
          "Camera.TrueEMGain": v["em_gain"]["median"],
          "Camera.ReadNoise": v["read_noise_e"]["median"],
          "Camera.NoiseFactor": 1.41 if v["em_gain"]["median"] > 1 else 1.0,
          # names beside pyme.json, never this machine's absolute paths: the folder moves
          "Camera.DarkMapID": files["dark"].name,
          "Camera.VarianceMapID": files["variance"].name,
          "Camera.FlatfieldMapID": files["flatfield"].name}
    if qe is not None:
        md["Camera.QuantumEfficiency"] = qe
    if pixel_size_nm is not None:
        md["voxelsize.x"] = md["voxelsize.y"] = pixel_size_nm / 1000.0  # µm
    md = {k: (_number(x) if isinstance(x, float) else x) for k, x in md.items()}
    md["emccdcal.Provenance"] = json.dumps(prov)
    text = json.dumps(md, indent=2, sort_keys=True) + "\n"
    return [_write_text(out / "pyme.json", text), *files.values()]


def _decode(cal, s, v, out, qe, pixel_size_nm, name):
    """DECODE ``param.yaml``'s ``Camera`` block (release 0.10 layout)."""
    camera = {"baseline": v["offset"]["median"], "convert2photons": True,
              "e_per_adu": v["e_per_adu"]["median"], "em_gain": v["em_gain"]["median"],
              "qe": 1.0 if qe is None else qe, "read_sigma": v["read_noise_e"]["median"],
              "spur_noise": 0.0}
    if pixel_size_nm is not None:
        camera["px_size"] = [pixel_size_nm, pixel_size_nm]  # nm, x and y
    text = _comment_lines(cal, s, v, qe, "# ") + _yaml({"Camera": camera})
    return [_write_text(out / "decode-camera.yaml", text)]


def _thunderstorm(cal, s, v, out, qe, pixel_size_nm, name):
    """An ImageJ macro line of ThunderSTORM's ``Camera setup`` (``photons2adu`` is φ in
    e⁻/ADU, despite its name)."""
    g = v["em_gain"]["median"]
    options = [f"offset={_number(v['offset']['median'])!r}",
               f"quantumefficiency={_number(1.0 if qe is None else qe)!r}",
               f"isemgain={'true' if g > 1 else 'false'}",
               f"photons2adu={_number(v['e_per_adu']['median'])!r}",
               f"gainem={_number(g)!r}"]
    if pixel_size_nm is not None:
        options.append(f"pixelsize={_number(pixel_size_nm)!r}")
    text = (_comment_lines(cal, s, v, qe, "// ")
            + f'run("Camera setup", "{" ".join(options)}");\n')
    return [_write_text(out / "thunderstorm-camera.ijm", text)]


def _smap(cal, s, v, out, qe, pixel_size_nm, name):
    """SMAP's camera settings (``loc_cameraSettings``: ``EMon``, ``emgain``, ``conversion``
    e⁻/ADU, ``offset`` ADU), as JSON and as a Camera Manager file (``smap-cameras.mat``),
    and its camera correction file (``offsetmap`` ADU, ``gainmap`` photons per ADU = φ/g,
    ``varmap`` ADU², indexed [row, col])."""
    from scipy.io import savemat

    offset, sigma = cal.dark(s)
    prov = _provenance(cal, s, qe)
    mat = out / "smap-correction.mat"
    maps = {"offsetmap": offset, "gainmap": cal.e_per_adu / cal.gain(s), "varmap": sigma ** 2}
    content = {k: np.asarray(m, dtype=np.float32) for k, m in maps.items()}
    atomic_write(mat, lambda p: savemat(p, {**content, "emccdcal": json.dumps(prov)}))
    par = {"EMon": bool(v["em_gain"]["median"] > 1), "emgain": _number(v["em_gain"]["median"]),
           "conversion": _number(v["e_per_adu"]["median"]),
           "offset": _number(v["offset"]["median"]),
           "correctionfile": mat.stem,
           "comment": f"emccdcal {prov['emccdcal_version']} {prov['method']} "
                      + " ".join(r["sha256"][:12] for r in prov["results"])}
    if pixel_size_nm is not None:
        par["cam_pixelsize_um"] = _number(pixel_size_nm / 1000.0)
    else:
        warnings.warn("SMAP's Camera Manager file holds a pixel size: SMAP's default "
                      "0.1 µm is written; give --pixel-size NM, or set it in the Camera "
                      "Manager", stacklevel=3)
    doc = {"loc_cameraSettings": par, "emccdcal": prov}
    cameras = out / "smap-cameras.mat"
    atomic_write(cameras, lambda p: savemat(p, _smap_camera_manager(par)))
    return [_write_text(out / "smap-camera.json", json.dumps(doc, indent=2) + "\n"), mat,
            cameras]


#: SMAP's Camera Manager parameter table (``CameraManager.m``, ``intpartable``): name,
#: mode, value of a new camera, conversion SMAP applies to the text. Rows SMAP reads from
#: the image files ("metadata") are left to them; the others are fixed to our numbers.
_SMAP_TABLE = (("EMon", "fix", "1", "str2double(X)"),
               ("cam_pixelsize_um", "fix", "0.1", "str2double(X)"),
               ("conversion", "fix", "1", "str2double(X)"),
               ("emgain", "fix", "100", "str2double(X)"),
               ("offset", "fix", "100", "str2double(X)"),
               ("roi", "fix", "", "str2num(X)"),
               ("exposure", "fix", "1", "str2double(X)"),
               ("timediff", "fix", "1", "str2double(X)"),
               ("comment", "fix", "settings not initialized", ""),
               ("numberOfFrames", "metadata", "0", "str2double(X)"),
               ("Width", "metadata", "0", "str2double(X)"),
               ("Height", "metadata", "0", "str2double(X)"),
               ("roimode", "fix", "none", ""),
               ("correctionfile", "fix", "", ""),
               ("imagemetadata", "fix", "", ""))


def _smap_camera_manager(par: dict) -> dict:
    """SMAP's camera database (the variables ``cameras`` and ``camtab`` its Camera Manager
    saves and ``getCameraCalibration`` reads) holding one camera named ``Default``: the
    one SMAP uses for files whose camera it does not recognise (a camera of another name
    would need an identifying metadata tag, which differs by adapter). Every number is
    fixed (mode ``fix``); the one state matches any file."""
    def text(key, value):
        if key == "EMon":
            return "1" if value else "0"
        return value if isinstance(value, str) else repr(float(value))

    values = {key: text(key, par[key]) if key in par else default
              for key, _, default, _ in _SMAP_TABLE}
    cells = lambda rows: np.array(rows, dtype=object)  # noqa: E731 - MATLAB cell arrays
    table = cells([[key, mode, values[key], "select", "", conversion, ""]
                   for key, mode, _, conversion in _SMAP_TABLE])
    state = {"statelist": cells([["State 1"]]), "defpar": cells([["select", ""]]),
             "par": cells([[key, values[key]] for key, *_ in _SMAP_TABLE])}
    entry = {"ID": {"name": "Default", "tag": "select", "value": ""}, "par": table,
             "state": state}
    return {"cameras": entry, "camtab": cells([["Default", "select", ""]])}


def _gdsc(cal, s, v, out, qe, pixel_size_nm, name):
    """gdsc-smlm's ``Calibration`` message as protobuf JSON (``count_per_photon`` is the
    total gain QE·g/φ in counts per photon; ``read_noise`` and ``bias`` in counts)."""
    q = 1.0 if qe is None else qe
    prov = _provenance(cal, s, qe)
    sha = ",".join(r["sha256"][:12] for r in prov["results"])
    message = {
        "intensityCalibration": {"intensityUnit": "COUNT",
                                 "countPerPhoton": _number(q * v["adu_per_e_total"]["median"])},
        "cameraCalibration": {"cameraType": "EMCCD",
                              "readNoise": _number(v["read_noise"]["median"]),
                              "bias": _number(v["offset"]["median"]),
                              "quantumEfficiency": _number(q),
                              # the one free-text field: the provenance (EMCCDs use no model)
                              "cameraModelName": f"emccdcal {prov['emccdcal_version']} "
                                                 f"{prov['method']} sha256 {sha}"},
    }
    if pixel_size_nm is not None:
        message["distanceCalibration"] = {"distanceUnit": "PIXEL",
                                          "nmPerPixel": _number(pixel_size_nm)}
    return [_write_text(out / "gdsc-calibration.json", json.dumps(message, indent=2) + "\n")]


def _storm_analysis(cal, s, v, out, qe, pixel_size_nm, name):
    """storm-analysis parameters (``camera_gain`` is g/φ in ADU per photoelectron, EM gain
    included; ``camera_offset`` ADU)."""
    comment = _comment_lines(cal, s, v, qe, "  ").replace("--", "- -")
    text = ('<?xml version="1.0" encoding="utf-8"?>\n<!--\n' + comment + "-->\n<settings>\n"
            f'  <camera_gain type="float">{_number(v["adu_per_e_total"]["median"])!r}'
            "</camera_gain>\n"
            f'  <camera_offset type="float">{_number(v["offset"]["median"])!r}'
            "</camera_offset>\n")
    if pixel_size_nm is not None:
        text += f'  <pixel_size type="float">{_number(pixel_size_nm)!r}</pixel_size>\n'
    text += "</settings>\n"
    return [_write_text(out / "storm-analysis.xml", text)]


def _all_values(cal):
    """:func:`camera_values` at every set-point with an offset; φ and g alone elsewhere."""
    doc = {}
    for s in cal.setpoints:
        if s in cal.offset:
            doc[format_setpoint(s)] = camera_values(cal, s)
        else:
            doc[format_setpoint(s)] = {"e_per_adu": pixel_statistics(cal.e_per_adu),
                                       "em_gain": pixel_statistics(cal.gain(s))}
    return doc


def _json(cal, s, v, out, qe, pixel_size_nm, name):
    """Everything, every set-point, in our own names and units."""
    doc = {"emccdcal": _provenance(cal, None, qe), "camera": cal.camera,
           "units": {"e_per_adu": "e-/ADU", "em_gain": "1", "adu_per_e_total": "ADU/e-",
                     "offset": "ADU", "read_noise": "ADU", "read_noise_e": "e-"},
           "statistics": "median over converged pixels; spread: robust spread 1.4826*MAD; "
                         "se_of_median: standard error of that median, "
                         "sqrt(pi/2)*spread/sqrt(n); n pixels (docs/results.md)",
           "by_setpoint": _all_values(cal)}
    if pixel_size_nm is not None:
        doc["pixel_size_nm"] = pixel_size_nm
    return [_write_text(out / "emccdcal-camera.json", json.dumps(doc, indent=2) + "\n")]


def _maps(cal):
    """Every per-pixel map: (name, image, unit)."""
    yield "e_per_adu", cal.e_per_adu, "e-/ADU"
    if cal.e_per_adu_se is not None:
        yield "e_per_adu_se", cal.e_per_adu_se, "e-/ADU"
    for s in cal.setpoints:
        tag = format_setpoint(s) + "x"
        if s in cal.em_gain:
            yield f"em_gain_{tag}", cal.gain(s), "1"
            yield f"em_gain_se_{tag}", cal.gain_se(s), "1"
        if s in cal.offset:
            yield f"offset_{tag}", cal.offset[s], "ADU"
            yield f"read_noise_{tag}", cal.read_noise[s], "ADU"


def _fits(cal, s, v, out, qe, pixel_size_nm, name):
    """One FITS file, an image extension per map (``EXTNAME``, ``BUNIT``)."""
    try:
        from astropy.io import fits
    except ImportError:
        raise OptionError("--to fits needs astropy: pip install 'emccdcal[fits]'") from None
    prov = _provenance(cal, None, qe)
    primary = fits.PrimaryHDU()
    primary.header["CREATOR"] = f"emccdcal {prov['emccdcal_version']}"
    primary.header["METHOD"] = prov["method"]
    primary.header["EMMODEL"] = prov["em_model"]
    primary.header["CALDATE"] = prov["created"]
    for i, r in enumerate(prov["results"]):
        primary.header[f"RESULT{i}"] = Path(r["file"]).name
        primary.header[f"SHA256{i}"] = r["sha256"][:64]
    if cal.origin is not None:
        primary.header["ORIGROW"], primary.header["ORIGCOL"] = cal.origin
    hdus = [primary]
    for key, image, unit in _maps(cal):
        hdu = fits.ImageHDU(np.asarray(image, dtype=np.float32), name=key.upper()[:68])
        hdu.header["BUNIT"] = unit
        hdus.append(hdu)
    path = out / "emccdcal-maps.fits"
    return [atomic_write(path, lambda p: fits.HDUList(hdus).writeto(p))]


def _tiff_maps(cal, s, v, out, qe, pixel_size_nm, name):
    """One float32 TIFF per map, its units and provenance in the description (JSON)."""
    prov = _provenance(cal, None, qe)
    return [_write_tiff(out / f"{key}.tif", image, {"quantity": key, "units": unit, **prov})
            for key, image, unit in _maps(cal)]


def export(calibration, to: str, out, *, setpoint=None, qe=None, pixel_size_nm=None,
           camera_name=None) -> list[Path]:
    """Write a calibration in a localization tool's own file.

    Parameters
    ----------
    calibration : Calibration, str or Path
        A :class:`~emccdcal.result.Calibration`, or a result (file or directory, or
        several joined by commas) to read with :func:`~emccdcal.result.load_calibration`.
    to : str
        One of :data:`TOOLS`: a tool registered under the entry-point group
        ``emccdcal.tools`` (:mod:`emccdcal.plugins`), emccdcal's own or another package's.
    out : str or Path
        Output directory (created if missing); files are written atomically.
    setpoint : float, optional
        The EM-gain set-point of the movies the tool will read (dimensionless); needed
        where the calibration has several multiplied set-points (not for ``json``,
        ``fits``, ``tiff-maps``, which take them all).
    qe : float, optional
        Quantum efficiency (photoelectrons per photon, 0–1) for tools that take it. Not
        given: tools that need it get 1, so their "photons" are photoelectrons.
    pixel_size_nm : float, optional
        Camera pixel size in the sample plane, nm; written where a tool takes it.
    camera_name : str, optional
        The camera's name in Picasso's configuration (default: model and serial as the
        files recorded them).

    Returns
    -------
    list of Path
        The files written.

    Raises
    ------
    OptionError
        An unknown tool, a set-point missing from the calibration (or needed and not
        given), a QE outside (0, 1], or no offset recorded at that set-point.
    """
    registered = plugins.load(plugins.TOOLS)
    if to not in registered:
        raise OptionError(f"unknown export target {to!r}; one of {', '.join(registered)}")
    tool = registered[to]
    if qe is not None and not (0 < qe <= 1):
        raise OptionError(f"--qe is photoelectrons per photon, in (0, 1]; got {qe}")
    if pixel_size_nm is not None and not (pixel_size_nm > 0 and math.isfinite(pixel_size_nm)):
        raise OptionError(f"--pixel-size is in nm and positive; got {pixel_size_nm}")
    cal = calibration if isinstance(calibration, Calibration) else load_calibration(calibration)
    if tool.all_setpoints:
        s, values = None, None
    else:  # refused before anything is made: no empty folder left behind
        s = pick_setpoint(cal, setpoint)
        values = camera_values(cal, s)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    return tool.write(cal, s, values, out, qe, pixel_size_nm, camera_name)


def export_modes(calibrations, to: str, out, *, setpoint=None, qe=None, pixel_size_nm=None,
                 camera_name=None) -> list[Path]:
    """Write several calibrations of one camera, one per read-out mode (output amplifier,
    read-out rate, pre-amplifier gain), as one tool file keyed by mode.

    Only Picasso's ``config.yaml`` holds such a table (its nested ``Sensitivity`` with
    ``Sensitivity Categories``); the other tools take one mode per file.

    Parameters
    ----------
    calibrations : sequence of Calibration, str or Path
        One per read-out mode, of one camera.
    to, out, setpoint, qe, pixel_size_nm, camera_name
        As :func:`export`; ``setpoint`` is needed where a mode has several multiplied
        set-points. A mode without multiplication enters at 1×. ``qe`` is accepted for
        the same call as :func:`export` and not written: Picasso uses no QE.

    Raises
    ------
    OptionError
        A tool other than Picasso, calibrations of different cameras, two of one mode,
        or a mode its files do not record.
    """
    if to != "picasso":
        raise OptionError(f"{to} takes one read-out mode per file, and the calibrations "
                          "given are of several: export each mode on its own (Picasso's "
                          "config.yaml holds a table of modes)")
    cals = [c if isinstance(c, Calibration) else load_calibration(c) for c in calibrations]
    serials = {c.camera.get("serial") for c in cals}
    if len(serials) > 1:
        raise OptionError("the calibrations are of different cameras (serials "
                          f"{', '.join(sorted(map(str, serials)))}); a table of read-out "
                          "modes is of one camera")
    multiplied = sorted({x for c in cals for x in c.setpoints if x != 1.0})
    if setpoint is None and len(multiplied) > 1:
        raise OptionError("the calibrations have set-points "
                          + ", ".join(format_setpoint(x) + "x" for x in multiplied)
                          + "; give --setpoint G (the set-point the movies were recorded at)")
    s = float(setpoint) if setpoint is not None else (multiplied[0] if multiplied else 1.0)
    rows = []  # refused before anything is made
    for c in cals:
        if s not in c.setpoints and len(c.setpoints) > 1:
            c.gain(s)  # raises, naming what it has
        at = s if s in c.setpoints else 1.0  # a mode without EM multiplication: 1x
        rows.append((c, at, camera_values(c, at)))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    return _picasso_modes(rows, s, out, pixel_size_nm, camera_name)
