"""``emccdcal audit``: are a localization tool's camera numbers right?

Reads the camera settings a user already has — Picasso's ``config.yaml``, a ThunderSTORM
``Camera setup`` macro, a DECODE ``param.yaml``, a gdsc-smlm ``Calibration``, SMAP's
camera settings (JSON or ``cameras.mat``), PYME metadata (JSON or ``.md``),
storm-analysis XML — and compares every number with a calibration, in the tool's own
words: each field against the calibrated quantity it stands for, and the photoelectrons
per ADU the tool's fields give together against the calibrated φ/g, which is by how much
the tool's photon counts are biased. What each field means, and its unit, is the table
of ``docs/exports.md`` (the same as ``emccdcal export`` writes).

The verdict: a photon bias beyond ``tolerance`` (2 % by default), or a baseline further
from the calibrated offset than the offset's own spread over the pixels plus 1 ADU, is
"off" (exit status 1 on the command line). A QE is not measured by a calibration: it is
checked only against one given (``qe``); a tool's photons are its photoelectrons / QE.

Examples
--------
>>> from emccdcal.export.audit import TOOL_NAMES
>>> TOOL_NAMES["thunderstorm"]
'ThunderSTORM'
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import _files, defaults, plugins
from .._output import comment
from .._util import one_line
from ..errors import EmccdcalError, InputError, OptionError
from ..model import adc
from ..result import format_setpoint, load_calibration
from .toolkit import QUANTITIES, Field, Reading, camera_values, mat_raw, pick_setpoint

__all__ = [
    "TOOL_NAMES",  # noqa: F822 (from the plug-ins, by __getattr__)
    "Field",
    "Reading",
    "Audit",
    "read_tool_file",
    "audit",
    "DEFAULT_TOLERANCE",
]  # (TOOL_NAMES from the plug-ins, by the module's __getattr__)

#: The photon bias beyond which an audit says "off", as a fraction.
DEFAULT_TOLERANCE = defaults.AUDIT_TOLERANCE


def _readable() -> dict:
    """The registered tools whose files an audit reads (:mod:`emccdcal.plugins`)."""
    return {
        n: t
        for n, t in plugins.load(plugins.TOOLS).items()
        if t.read is not None or t.read_file is not None
    }


def __getattr__(name):
    if name == "TOOL_NAMES":  # the tools an audit reads: --tool's name → the tool's own
        return {n: t.title for n, t in _readable().items()}
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


@dataclass
class Audit:
    """The comparison of one :class:`Reading` with a calibration at one set-point."""

    reading: Reading
    setpoint: float
    rows: list[dict]  # {"field", "text"}
    calibrated_pe_per_adu: float  # φ/g, medians over the converged pixels
    photon_bias: float
    offset_error: float | None
    offset_tolerance: float
    tolerance: float
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    def lines(self) -> list[str]:
        """The audit as the console shows it."""
        r = self.reading
        # where and the rows quote the tool's file: data, each on its one line
        out = [
            f"{_readable()[r.tool].title}: {comment(r.where)} "
            f"(set-point {format_setpoint(self.setpoint)}x)"
        ]
        width = max(len(row["field"]) for row in self.rows)
        for row in self.rows:
            out.append(f"  {comment(row['field']):<{width}}  {comment(row['text'])}")
        out.append(
            f"  photons: {r.formula} = {r.pe_per_adu:.6g} e-/ADU against the "
            f"calibrated phi/g = {self.calibrated_pe_per_adu:.6g}: "
            f"{_percent(self.photon_bias, 2)}"
        )
        verdict = "OK" if self.ok else "OFF"
        out.append(
            f"  {verdict}: "
            + (
                "; ".join(self.problems)
                if self.problems
                else f"photons within {100 * self.tolerance:g} %, baseline within "
                f"{self.offset_tolerance:.3g} ADU"
            )
        )
        return out


# --------------------------------------------------------------------------------------
# Reading the tools' files
# --------------------------------------------------------------------------------------
def _mat_tree(path):
    """A MATLAB file as nested dicts (structs become dicts)."""
    raw = mat_raw(path, squeeze=True)

    def convert(value, depth=0):
        if depth > 20:
            return None
        if hasattr(value, "_fieldnames"):
            return {n: convert(getattr(value, n), depth + 1) for n in value._fieldnames}
        if isinstance(value, np.ndarray) and value.dtype == object:
            return [convert(v, depth + 1) for v in value.reshape(-1)]
        return value

    return {k: convert(v) for k, v in raw.items() if not k.startswith("__")}


def _percent(fraction: float, decimals: int) -> str:
    """A relative difference as a signed percentage, ``"+4.77 %"``; beyond a million per
    cent (a number of another unit, or typed wrong) in three significant digits, never
    three hundred of them."""
    value = 100 * fraction
    if abs(value) < 1e6:
        return f"{value:+.{decimals}f} %"
    return f"{value:+.3g} %"


def _guess_tool(path: Path, text: str | None, doc) -> str:
    """The first registered tool that recognises the file as its own."""
    readable = _readable()
    for name, tool in readable.items():
        if tool.recognizes is not None and _asking(tool, tool.recognizes, path, text, doc):
            return name
    raise InputError(
        f"'{path}': not a camera file of a tool emccdcal knows "
        f"({', '.join(t.title for t in readable.values())}); give --tool NAME "
        "if it is one"
    )


def read_tool_file(path, *, tool=None, setpoint=1.0, tool_gain=None) -> list[Reading]:
    """The camera entries of a localization tool's file.

    Parameters
    ----------
    path : str or Path
        The file: Picasso ``config.yaml``, ThunderSTORM macro (``.ijm``/``.txt``),
        DECODE ``.yaml``, gdsc-smlm ``.json``, SMAP ``.json`` or ``cameras.mat``, PYME
        ``.json`` or ``.md``, storm-analysis ``.xml``.
    tool : str, optional
        One of :data:`TOOL_NAMES` (a registered tool that reads its files back,
        :mod:`emccdcal.plugins`); default: the first that recognises the file.
    setpoint : float
        The set-point the tool's movies are taken at: Picasso's EM gain where its file
        holds none (users type the set-point into its gain box).
    tool_gain : float, optional
        The EM gain typed into the tool, where its file has none (Picasso).

    Raises
    ------
    InputError
        An unreadable file, one of no known tool, or a field that is not a number.
    """
    path = Path(path)
    _files.read_bytes(path, what="tool's settings file", max_bytes=_files.MAX_MAT_BYTES)
    readable = _readable()
    if tool is not None and tool not in readable:
        raise OptionError(f"unknown tool {tool!r}; one of {', '.join(readable)}")
    text, doc = None, None
    if path.suffix.lower() in (".mat", ".tif", ".tiff"):
        # a tool that reads its own binary files (SMAP's camera manager, gdsc-smlm's
        # per-pixel camera model) is asked first
        refused = None  # a tool's reason that the file is not its own, for the message
        for name, t in readable.items():
            if t.read_file is not None and tool in (None, name):
                try:
                    found = _asking(t, t.read_file, path, setpoint)
                except InputError as exc:
                    refused = refused or exc
                    continue
                if found is not None:
                    return found
        if refused is not None and (tool is None or readable[tool].read is None):
            raise refused
        if tool is not None and readable[tool].read is None:
            raise InputError(f"'{path}': not a {readable[tool].title} file")
        if path.suffix.lower() != ".mat":
            raise InputError(
                f"'{path}': not a camera model of a tool emccdcal knows (gdsc-smlm's "
                "per-pixel camera model is the TIFF it reads)"
            )
        doc = _mat_tree(path)
    elif path.suffix.lower() != ".xml":
        text = _files.read_text(path, what="tool's settings file")
        doc = _parse_text(path, text)
    tool = tool or _guess_tool(path, text, doc)
    readings = _asking(readable[tool], readable[tool].read, path, text, doc, setpoint, tool_gain)
    if not isinstance(readings, list) or not all(isinstance(r, Reading) for r in readings):
        raise InputError(f"'{path}': {readable[tool].title}'s reader gives no list of readings")
    return readings


def _asking(tool, function, path, *args):
    """``function(path, *args)`` of a tool (its reader, recogniser): what it raises on a
    file it cannot read (a damaged one, a field it lacks; a plug-in's mistake) is one
    line naming the file, never a traceback from inside the tool."""
    try:
        return function(path, *args)
    except EmccdcalError:
        raise
    except Exception as exc:  # noqa: BLE001 - whatever the file broke, in one line
        raise InputError(
            f"'{path}': {tool.title} cannot read it ({type(exc).__name__}: {one_line(exc)})"
        ) from None


def _parse_text(path: Path, text: str):
    """JSON, else YAML, else None (a macro or PYME's ``.md``)."""
    if path.suffix.lower() in (".ijm", ".txt", ".md"):
        return None
    if text.lstrip().startswith(("{", "[")):
        return _files.load_json(path, text=text, what="tool's settings file")
    try:
        return _files.load_yaml(path, text=text, what="tool's settings file")
    except InputError as exc:
        raise InputError(f"{exc} (neither JSON nor YAML)") from None


# --------------------------------------------------------------------------------------
# Comparing
# --------------------------------------------------------------------------------------
def _compare(reading: Reading, values: dict, setpoint, tolerance, offset_tolerance, qe):
    truth = {k: values[k]["median"] for k in QUANTITIES}
    # photoelectrons per ADU, from the same references as the tool's own rows: a tool
    # holding g/φ as one number (gdsc-smlm, storm-analysis) against the median over
    # pixels of g/φ, one holding φ and g against their medians, so that a file whose
    # every row agrees reads no photon bias
    combined = any(f.quantity == "adu_per_e_total" for f in reading.fields)
    pe_per_adu = (
        1.0 / truth["adu_per_e_total"] if combined else truth["e_per_adu"] / truth["em_gain"]
    )
    rows = []
    for f in reading.fields:
        row = {"field": f.name}
        note = f" ({f.note})" if f.note else ""
        if f.quantity == "offset":
            diff = f.value - truth["offset"]
            row["text"] = (
                f"{f.value:.6g} ADU; calibrated offset {truth['offset']:.6g} ADU: "
                f"{diff:+.3g} ADU ({-diff * pe_per_adu:+.3g} e- per pixel and frame)" + note
            )
        elif f.quantity in QUANTITIES:
            unit, what = QUANTITIES[f.quantity]
            rel = f.value / truth[f.quantity] - 1
            row["text"] = (
                f"{f.value:.6g} {unit}".rstrip() + f"; calibrated {what} "
                f"{truth[f.quantity]:.6g}: {_percent(rel, 2)}{note}"
            )
        else:  # a number of the tool's that no calibrated quantity stands for alone
            row["text"] = f"{f.value:.6g} (compared only in the photons){note}"
        rows.append(row)
    if reading.qe is not None:
        text = f"{reading.qe:g}: photons = photoelectrons / {reading.qe:g}"
        if qe is not None:
            text += f"; given QE {qe:g}: {_percent(reading.qe / qe - 1, 2)}"
        rows.append({"field": "QE", "text": text})
    bias = reading.pe_per_adu / pe_per_adu - 1
    spread = values["offset"]["spread"] or 0.0
    tol_offset = spread + 1.0 if offset_tolerance is None else offset_tolerance
    offset_error = None if reading.baseline is None else reading.baseline - truth["offset"]
    problems = []
    if abs(bias) > tolerance:
        worst = max(
            (
                f
                for f in reading.fields
                if f.quantity in ("e_per_adu", "em_gain", "adu_per_e_total")
            ),
            key=lambda f: abs(math.log(f.value / truth[f.quantity])),
            default=None,
        )
        name = f" (most of it {worst.name})" if worst is not None else ""
        problems.append(
            f"photons {_percent(bias, 1)}{name}, beyond {100 * tolerance:g} %: "
            f"{reading.formula} should be {pe_per_adu:.6g} e-/ADU"
        )
    if offset_error is not None and abs(offset_error) > tol_offset:
        base = next(f.name for f in reading.fields if f.quantity == "offset")
        problems.append(
            f"{base} {offset_error:+.3g} ADU from the calibrated offset "
            f"{truth['offset']:.6g} ADU, beyond {tol_offset:.3g} ADU"
        )
    if qe is not None and reading.qe is not None and abs(reading.qe / qe - 1) > tolerance:
        problems.append(
            f"QE {reading.qe:g} but {qe:g} given: photons {_percent(qe / reading.qe - 1, 1)}"
        )
    return Audit(
        reading, setpoint, rows, pe_per_adu, bias, offset_error, tol_offset, tolerance, problems
    )


def audit(
    toolfile,
    calibration,
    *,
    setpoint=None,
    tool=None,
    tool_gain=None,
    qe=None,
    tolerance=DEFAULT_TOLERANCE,
    offset_tolerance=None,
) -> list[Audit]:
    """Compare a localization tool's camera numbers with a calibration.

    Parameters
    ----------
    toolfile : str or Path
        The tool's file (:func:`read_tool_file`).
    calibration : xarray.Dataset, Calibration, str or Path
        A calibration, or its result file or directory (several joined by commas).
    setpoint : float, optional
        The EM-gain set-point of the tool's movies (needed where the calibration has
        several multiplied set-points).
    tool, tool_gain : optional
        As :func:`read_tool_file`.
    qe : float, optional
        The quantum efficiency at the emission wavelength, to check the tool's against.
    tolerance : float
        The photon bias (a fraction) beyond which the tool is "off".
    offset_tolerance : float, optional
        ADU; default the calibrated offset's spread over pixels plus 1 ADU.

    Returns
    -------
    list of Audit
        One per camera entry of the file (read-out modes of a nested table that the
        calibration's recorded read-out state singles out are kept alone).

    Examples
    --------
    >>> import tempfile, emccdcal
    >>> work = tempfile.mkdtemp()
    >>> sim = emccdcal.simulate_gain_series(
    ...     f"{work}/gs", rows=4, cols=4, frames=400, setpoints=(1, 10), seed=1, progress=False
    ... )
    >>> ds = emccdcal.calibrate(sim.manifest, e_per_adu=sim.truth["e_per_adu"], progress=False)
    >>> files = emccdcal.export_calibration(ds, "picasso", f"{work}/picasso", setpoint=10)
    >>> [a.ok for a in emccdcal.audit(files[0], ds, setpoint=10)]
    [True]
    """
    if not (0 < tolerance < 1):
        raise OptionError(f"tolerance is a fraction in (0, 1); got {tolerance}")
    if qe is not None and not (0 < qe <= 1):
        raise OptionError(f"--qe is photoelectrons per photon, in (0, 1]; got {qe}")
    cal = load_calibration(calibration)
    s = pick_setpoint(cal, setpoint)
    values = camera_values(cal, s)
    readings = _matching(
        read_tool_file(toolfile, tool=tool, setpoint=s, tool_gain=tool_gain), cal.camera
    )
    audits = [_compare(r, values, s, tolerance, offset_tolerance, qe) for r in readings]
    for a in audits:
        if a.reading.maps is not None:
            _per_pixel(a, cal, s, qe, offset_tolerance)
    return audits


def _per_pixel(a: Audit, cal, s, qe, offset_tolerance) -> None:
    """Add to ``a`` the comparison of its reading's per-pixel maps with the calibration's,
    placed by the two sensor origins: the photons, the baseline and the variance of every
    pixel the calibration converged at, the worst named."""
    maps, r = a.reading.maps, a.reading
    rows, cols = maps["offset"].shape
    r0, c0 = (0, 0)
    if r.origin is not None and cal.origin is not None:
        r0, c0 = r.origin[0] - cal.origin[0], r.origin[1] - cal.origin[1]
    R, C = cal.e_per_adu.shape
    if r0 < 0 or c0 < 0 or r0 + rows > R or c0 + cols > C:
        a.problems.append(
            f"its {rows} x {cols} pixels at sensor (row, col) {r.origin} are not all in the "
            f"calibration's {R} x {C} at {cal.origin}"
        )
        return
    region = (slice(r0, r0 + rows), slice(c0, c0 + cols))
    offset, sigma = (m[region] for m in cal.dark(s))
    gain = ((1.0 if qe is None else qe) * cal.gain(s) / cal.e_per_adu)[region]
    variance = adc.count_variance(sigma, s == 1)
    ok = np.isfinite(offset) & np.isfinite(gain) & np.isfinite(variance)
    photons = np.where(ok, gain / maps["adu_per_e_total"] - 1.0, 0.0)
    baseline = np.where(ok, maps["offset"] - offset, 0.0)
    spread = np.where(ok, maps["variance"] / variance - 1.0, 0.0)

    def worst(diff, unit):
        i = np.unravel_index(int(np.argmax(np.abs(diff))), diff.shape)
        value = _percent(float(diff[i]), 2) if unit == "%" else f"{float(diff[i]):+.3g} ADU"
        return f"{value} at (row, col) ({i[0] + r0}, {i[1] + c0})"

    n = int(ok.sum())
    a.rows += [
        {"field": "per pixel", "text": f"{n} pixels compared (the calibration's converged ones)"},
        {"field": "  photons", "text": "worst " + worst(photons, "%")},
        {"field": "  baseline", "text": "worst " + worst(baseline, "ADU")},
        {"field": "  variance", "text": "worst " + worst(spread, "%")},
    ]
    off = np.abs(photons) > a.tolerance
    if off.any():
        a.problems.append(
            f"photons beyond {100 * a.tolerance:g} % at {int(off.sum())} of {n} pixels "
            f"(worst {worst(photons, '%')})"
        )
    limit = 1.0 if offset_tolerance is None else offset_tolerance
    far = np.abs(baseline) > limit
    if far.any():
        a.problems.append(
            f"baseline beyond {limit:g} ADU of the offset at {int(far.sum())} of {n} pixels "
            f"(worst {worst(baseline, 'ADU')})"
        )


def _matching(readings, camera: dict):
    """The entries of a nested read-out table that the calibration's recorded output
    amplifier, read-out rate (MHz) and analog gain name, where exactly one does; else
    all. A setting the table is not keyed by (no entry names it) does not narrow."""
    if len(readings) < 2:
        return readings
    wanted = []
    amplifier = camera.get("amplifier")
    if amplifier is not None:
        wanted.append(lambda where, a=str(amplifier): a in where.split(" > "))
    rate = camera.get("readout_rate_mhz")
    if rate is not None:
        wanted.append(
            lambda where, r=float(rate): any(
                abs(float(m) - r) < 1e-6 for m in re.findall(r"([0-9.]+)\s*MHz", where)
            )
        )
    analog = camera.get("analog_gain")
    if analog is not None:
        number = re.findall(r"[0-9.]+", str(analog))
        wanted.append(
            lambda where, n=number: (
                bool(n) and any(n[0] == m for m in re.findall(r"[Gg]ain\s*([0-9.]+)", where))
            )
        )
    chosen = readings
    for w in wanted:
        narrowed = [r for r in chosen if w(r.where)]
        if narrowed:  # a setting no entry names is not a key of the table
            chosen = narrowed
    return chosen if len(chosen) == 1 else readings
