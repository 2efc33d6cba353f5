"""The tool kit: what every localization tool's module is made of, emccdcal's own and a
stranger's (docs/plugins.md).

A tool (:class:`emccdcal.plugins.Tool`) writes a calibration in its own file and, for an
audit, reads such a file back. Both sides need the same few parts, all here and public:

- the numbers a tool takes at a set-point (:func:`pick_setpoint`, :func:`camera_values`)
  and the read-out mode they hold for (:data:`MODE_FIELDS`, :func:`readout_mode`,
  :func:`mode_key`);
- what a file records of where it came from (:func:`provenance`, :func:`comment_lines`,
  :func:`camera_name`, :func:`comment`) and how it writes (:func:`rounded`,
  :func:`yaml_text`, :func:`write_text`, :func:`write_file`, :func:`write_tiff`);
- what an audit reads (:class:`Field`, :class:`Reading`, :data:`QUANTITIES`,
  :func:`per_pixel_reading` for a tool's per-pixel maps) and how a file's values are
  checked (:func:`number`, :func:`positive`, :func:`quantum_efficiency`) and found
  (:func:`leaves`, :func:`find_tables`, :func:`mat_raw`, :func:`mat_scalar`,
  :func:`load_xml`, :func:`load_json`); and :func:`install_hint` for a tool that needs an
  extra.

This module imports no tool and no verb: the tools import it, and the verbs
(:mod:`emccdcal.export.tools`, :mod:`emccdcal.export.audit`) import it and the tools
through the registry, so no import goes round in a circle.

Examples
--------
>>> from emccdcal.export.toolkit import yaml_text, rounded
>>> print(yaml_text({"Camera": {"baseline": rounded(100.00000001)}}), end="")
"Camera":
  "baseline": 100.0
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import _files
from .._output import atomic_write, atomic_write_text, comment
from .._util import install_hint
from ..errors import InputError, OptionError
from ..result import Calibration, format_setpoint, pixel_statistics

__all__ = [
    "pick_setpoint",
    "camera_values",
    "MODE_FIELDS",
    "readout_mode",
    "mode_key",
    "provenance",
    "comment_lines",
    "camera_name",
    "rounded",
    "yaml_text",
    "write_text",
    "write_file",
    "write_tiff",
    "comment",
    "install_hint",
    "load_xml",
    "load_json",
    "QUANTITIES",
    "Field",
    "Reading",
    "number",
    "positive",
    "quantum_efficiency",
    "per_pixel_reading",
    "leaves",
    "find_tables",
    "mat_raw",
    "mat_scalar",
]

#: ``write_text(path, text)``: a text file written atomically (a reader never sees half
#: of it, an interrupted write leaves any earlier file as it was).
write_text = atomic_write_text
#: ``write_file(path, write)``: any file, atomically, by ``write(temporary_path)`` (a
#: writer of another library: ``savemat``, an HDU list's ``writeto``).
write_file = atomic_write
#: ``comment(text)``: text from a file on one line, control characters escaped, for a
#: comment of a text format (a serial or a path is data, never a line of its own).
#: ``install_hint(extra)``: how a message says to install one of emccdcal's extras.
#: ``load_xml(path, what=...)``: an XML file's root element, bounded, no entities.
load_xml = _files.load_xml
#: ``load_json(path, what=..., text=None)``: a JSON file (or its text), bounded, NaN refused.
load_json = _files.load_json


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
        raise OptionError(
            f"{cal.label}: has set-points {have}; a tool takes the gain of one: "
            "give --setpoint G (the set-point the movies were recorded at)"
        )
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
    values = {
        "e_per_adu": phi,
        "em_gain": gain,
        "adu_per_e_total": gain / phi,
        "offset": offset,
        "read_noise": sigma,
        "read_noise_e": sigma * phi,
    }
    out = {k: pixel_statistics(v) for k, v in values.items()}
    for name, stats in out.items():
        if stats["median"] is None or not math.isfinite(stats["median"]):
            raise OptionError(
                f"{cal.label}: no converged pixel has a finite {name} at "
                f"set-point {format_setpoint(setpoint)}x"
            )
    return out


#: The camera settings that make a read-out mode, with the Micro-Manager property names
#: of Andor's adapter, which Picasso matches its ``Sensitivity Categories`` against.
MODE_FIELDS = {
    "amplifier": "Output_Amplifier",
    "readout_rate_mhz": "ReadoutMode",
    "analog_gain": "Pre-Amp-Gain",
}


def readout_mode(cal: Calibration) -> tuple:
    """The calibration's read-out mode as its files recorded it: ``(amplifier, read-out
    rate in MHz, analog gain)``, ``None`` where not recorded."""
    return tuple(cal.camera.get(k) for k in MODE_FIELDS)


def mode_key(field_name, value) -> str:
    """A mode's value as Micro-Manager's Andor adapter writes it ("17.000 MHz")."""
    return f"{float(value):.3f} MHz" if field_name == "readout_rate_mhz" else str(value)


def provenance(cal: Calibration, setpoint=None, qe=None) -> dict:
    """What a file records of where its numbers came from (JSON-ready)."""
    doc = cal.provenance()
    if setpoint is not None:
        doc["setpoint"] = setpoint
    if qe is not None:
        doc["quantum_efficiency_given"] = qe
    return doc


def comment_lines(cal, setpoint, values, qe, prefix) -> str:
    """Provenance and the pixels' spread, as comment lines of a text format."""
    p = provenance(cal, setpoint, qe)
    lines = [
        f"written by emccdcal {p['emccdcal_version']} from {p['method']} "
        f"({p['em_model']} register), calibration of {p['created']}",
        f"at EM gain set-point {format_setpoint(setpoint)}x; medians over "
        f"{values['e_per_adu']['n']} converged pixels (robust spread in brackets):",
    ]
    for name, unit in (
        ("e_per_adu", "e-/ADU"),
        ("em_gain", ""),
        ("offset", "ADU"),
        ("read_noise", "ADU"),
    ):
        v = values[name]
        spread = "n/a" if v["spread"] is None else f"{v['spread']:.4g}"
        lines.append(f"  {name} = {v['median']:.6g} {unit} ({spread})")
    lines += [f"result {r['file']} sha256 {r['sha256']}" for r in p["results"]]
    if setpoint in cal.predicted:
        g = cal.predicted[setpoint]
        lines.append(
            f"the gain at {format_setpoint(setpoint)}x was not measured: "
            f"{g['gain']:.6g} +/- {g['se_of_median']:.2g} (se_of_median) predicted by "
            f"the gain curve {g['curve']}; extrapolated = "
            f"{str(g['extrapolated']).lower()}"
        )
    return "".join(f"{prefix}{comment(line)}\n" for line in lines)  # paths are data


def rounded(x) -> float:
    """A number as files write it: seven significant digits, far below any
    calibration's error."""
    return float(f"{float(x):.7g}")


def yaml_text(doc: dict, indent: int = 0) -> str:
    """A nested dict of scalars (and lists of them) as block YAML; string keys and values
    double-quoted, as JSON strings are valid YAML.

    >>> print(yaml_text({"Camera": {"baseline": 100.0, "px_size": [100, 100]}}), end="")
    "Camera":
      "baseline": 100.0
      "px_size": [100, 100]
    """
    out = []
    for key, value in doc.items():
        k = json.dumps(key) if isinstance(key, str) else str(key)
        if isinstance(value, dict):
            out.append(f"{' ' * indent}{k}:\n{yaml_text(value, indent + 2)}")
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
        return repr(rounded(value)) if isinstance(value, (float, np.floating)) else str(value)
    return json.dumps(str(value))


def write_tiff(path: Path, image, description: dict) -> Path:
    """A float32 TIFF of one map (atomically), ``description`` as its JSON description."""
    import tifffile

    data = np.asarray(image, dtype=np.float32)
    return atomic_write(
        path,
        lambda p: tifffile.imwrite(p, data, description=json.dumps(description), metadata=None),
    )


def camera_name(cal: Calibration, name) -> str:
    """The camera's name in a tool's file: ``name`` where given, else the model and
    serial its files recorded."""
    if name:
        return str(name)
    parts = [cal.camera.get("model"), cal.camera.get("serial")]
    return " ".join(str(p) for p in parts if p) or "EMCCD (emccdcal)"


# --------------------------------------------------------------------------------------
# What an audit reads
# --------------------------------------------------------------------------------------
#: What a field can stand for: the calibrated quantity, its unit, how to say it.
QUANTITIES = {
    "offset": ("ADU", "offset"),
    "e_per_adu": ("e-/ADU", "phi"),
    "em_gain": ("", "EM gain"),
    "adu_per_e_total": ("ADU/e-", "g/phi"),
    "read_noise": ("ADU", "read noise"),
    "read_noise_e": ("e-", "read noise x phi"),
}


@dataclass(frozen=True)
class Field:
    """One number of a tool's file: its name there, value, and the calibrated quantity
    it stands for (a key of ``QUANTITIES``, or ``"qe"``, or None: not comparable)."""

    name: str
    value: float
    quantity: str | None
    note: str = ""


@dataclass(frozen=True)
class Reading:
    """One camera entry of a tool's file (one read-out mode of a nested table).

    ``pe_per_adu`` is the photoelectrons per ADU (after the baseline) the tool's fields
    give together, QE aside; ``baseline`` the ADU it subtracts (None: not in the file).
    """

    tool: str
    where: str
    fields: tuple[Field, ...]
    pe_per_adu: float
    formula: str
    baseline: float | None = None
    qe: float | None = None
    #: Per-pixel maps of a tool that keeps them (a camera model of every pixel):
    #: ``{"offset": ADU, "adu_per_e_total": QE·g/φ, "variance": ADU²}``, (rows, cols)
    #: each, and the sensor pixel (row, col) of their first; audited pixel by pixel.
    maps: dict | None = None
    origin: tuple | None = None


def per_pixel_reading(
    tool, where, path, maps, origin=None, *, names, gain_note="", formula=None, partial=False
) -> list[Reading]:
    """The :class:`Reading` of a tool's per-pixel maps, checked: ``maps`` is
    ``{"offset": ADU, "adu_per_e_total": ADU/e⁻, "variance": ADU²}``, (rows, cols) each;
    ``names`` the file's names of the offset and the gain, for its fields and messages;
    ``origin`` the sensor (row, col) of its first pixel, where the file says;
    ``partial``: NaN (a pixel the file leaves out) allowed in the gain. Its fields are the
    medians; ``formula`` says how the photons per ADU follow (default 1 / the gain's)."""
    offset_name, gain_name = names
    shapes = {np.shape(m) for m in maps.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise InputError(f"'{path}': its maps ({', '.join(names)} ...) are not maps of one shape")
    gain = np.asarray(maps["adu_per_e_total"], dtype=float)
    given = np.isfinite(gain) if partial else np.ones(gain.shape, dtype=bool)
    if not given.any() or not np.all(np.isfinite(gain[given]) & (gain[given] > 0)):
        raise InputError(f"'{path}': its {gain_name} holds values that are not positive numbers")
    median_gain = float(np.median(gain[given]))
    baseline = float(np.nanmedian(maps["offset"]))
    fields = (
        Field(f"{offset_name} (median)", baseline, "offset"),
        Field(f"{gain_name} (median)", median_gain, "adu_per_e_total", gain_note),
    )
    formula = formula or f"1 / {gain_name} (median)"
    return [Reading(tool, where, fields, 1.0 / median_gain, formula, baseline, None, maps, origin)]


def number(value, what, path):
    """A tool file's value as a finite float, or one line naming the file and the field."""
    if isinstance(value, bool):  # YAML's true is not 1
        raise InputError(f"'{path}': {what} is {value!r}, not a number")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise InputError(f"'{path}': {what} is {value!r}, not a number") from None
    if not math.isfinite(x):
        raise InputError(f"'{path}': {what} is {value!r}, not a finite number")
    return x


def positive(value, what, path):
    """As :func:`number`, and > 0."""
    x = number(value, what, path)
    if x <= 0:
        raise InputError(f"'{path}': {what} is {value!r}; it must be > 0")
    return x


def quantum_efficiency(value, what, path):
    """A quantum efficiency: a number in (0, 1] (a percentage or a sign error refused)."""
    x = number(value, what, path)
    if not 0 < x <= 1:
        raise InputError(f"'{path}': {what} is {value!r}; a quantum efficiency lies in (0, 1]")
    return x


def leaves(tree, path=()):
    """(keys, value) of every non-mapping leaf of nested mappings."""
    if isinstance(tree, dict):
        for key, value in tree.items():
            yield from leaves(value, (*path, str(key)))
    else:
        yield path, tree


def find_tables(tree, keys, path=()):
    """(path, table) of every mapping in ``tree`` holding all of ``keys``."""
    if isinstance(tree, dict):
        if all(k in tree for k in keys):
            yield path, tree
        for key, value in tree.items():
            yield from find_tables(value, keys, (*path, str(key)))
    elif isinstance(tree, list):
        for i, value in enumerate(tree):
            yield from find_tables(value, keys, (*path, f"[{i}]"))


def mat_scalar(value):
    """A MATLAB value read by SciPy (an array of one element) as a Python scalar."""
    arr = np.asarray(value)
    if arr.size != 1:
        return value
    item = arr.reshape(-1)[0]
    return item.item() if hasattr(item, "item") else item


def mat_raw(path, squeeze=False):
    """A MATLAB file's variables as SciPy reads them (structs as objects)."""
    from scipy.io import loadmat

    _files.check_mat(path)
    try:
        return loadmat(path, squeeze_me=squeeze, struct_as_record=False)
    except Exception as exc:  # noqa: BLE001 - a damaged file is one line
        raise InputError(f"'{path}': not a readable MATLAB file ({exc})") from None
