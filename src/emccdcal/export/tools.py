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
from pathlib import Path

import numpy as np

from .. import plugins
from .._output import atomic_write, comment
from ..errors import OptionError
from ..result import Calibration, format_setpoint, load_calibration, pixel_statistics

# TOOLS comes from the plug-ins, by the module's __getattr__
__all__ = [
    "TOOLS",  # noqa: F822 (from the plug-ins, by __getattr__)
    "export",
    "export_modes",
    "camera_values",
    "readout_mode",
    "MODE_FIELDS",
]


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
    return atomic_write(
        path,
        lambda p: tifffile.imwrite(p, data, description=json.dumps(description), metadata=None),
    )


def _camera_name(cal: Calibration, name) -> str:
    if name:
        return str(name)
    parts = [cal.camera.get("model"), cal.camera.get("serial")]
    return " ".join(str(p) for p in parts if p) or "EMCCD (emccdcal)"


def export(
    calibration, to: str, out, *, setpoint=None, qe=None, pixel_size_nm=None, camera_name=None
) -> list[Path]:
    """Write a calibration in a localization tool's own file.

    Parameters
    ----------
    calibration : xarray.Dataset, Calibration, str or Path
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

    Examples
    --------
    >>> import tempfile, emccdcal
    >>> work = tempfile.mkdtemp()
    >>> sim = emccdcal.simulate_gain_series(
    ...     f"{work}/gs", rows=4, cols=4, frames=400, setpoints=(1, 10), seed=1, progress=False
    ... )
    >>> ds = emccdcal.calibrate(sim.manifest, e_per_adu=sim.truth["e_per_adu"], progress=False)
    >>> [p.name for p in emccdcal.export_calibration(ds, "picasso", f"{work}/p", setpoint=10)]
    ['picasso-config.yaml']
    """
    registered = plugins.load(plugins.TOOLS)
    if to not in registered:
        raise OptionError(f"unknown export target {to!r}; one of {', '.join(registered)}")
    tool = registered[to]
    if qe is not None and not (0 < qe <= 1):
        raise OptionError(f"--qe is photoelectrons per photon, in (0, 1]; got {qe}")
    if pixel_size_nm is not None and not (pixel_size_nm > 0 and math.isfinite(pixel_size_nm)):
        raise OptionError(f"--pixel-size is in nm and positive; got {pixel_size_nm}")
    cal = load_calibration(calibration)
    if tool.all_setpoints:
        s, values = None, None
    else:  # refused before anything is made: no empty folder left behind
        s = pick_setpoint(cal, setpoint)
        values = camera_values(cal, s)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    return tool.write(cal, s, values, out, qe, pixel_size_nm, camera_name)


def export_modes(
    calibrations, to: str, out, *, setpoint=None, qe=None, pixel_size_nm=None, camera_name=None
) -> list[Path]:
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
        raise OptionError(
            f"{to} takes one read-out mode per file, and the calibrations "
            "given are of several: export each mode on its own (Picasso's "
            "config.yaml holds a table of modes)"
        )
    cals = [load_calibration(c) for c in calibrations]
    serials = {c.camera.get("serial") for c in cals}
    if len(serials) > 1:
        raise OptionError(
            "the calibrations are of different cameras (serials "
            f"{', '.join(sorted(map(str, serials)))}); a table of read-out "
            "modes is of one camera"
        )
    multiplied = sorted({x for c in cals for x in c.setpoints if x != 1.0})
    if setpoint is None and len(multiplied) > 1:
        raise OptionError(
            "the calibrations have set-points "
            + ", ".join(format_setpoint(x) + "x" for x in multiplied)
            + "; give --setpoint G (the set-point the movies were recorded at)"
        )
    s = float(setpoint) if setpoint is not None else (multiplied[0] if multiplied else 1.0)
    rows = []  # refused before anything is made
    for c in cals:
        if s not in c.setpoints and len(c.setpoints) > 1:
            c.gain(s)  # raises, naming what it has
        at = s if s in c.setpoints else 1.0  # a mode without EM multiplication: 1x
        rows.append((c, at, camera_values(c, at)))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    from .toolfiles import picasso

    return picasso.write_modes(rows, s, out, pixel_size_nm, camera_name)
