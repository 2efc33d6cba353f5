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
from ..errors import InputError, OptionError
from ..result import Calibration, format_setpoint, load_calibration
from .tools import camera_values, pick_setpoint

__all__ = ["TOOL_NAMES", "Field", "Reading", "Audit", "read_tool_file", "audit",
           "DEFAULT_TOLERANCE"]

#: The photon bias beyond which an audit says "off", as a fraction.
DEFAULT_TOLERANCE = defaults.AUDIT_TOLERANCE


def _readable() -> dict:
    """The registered tools whose files an audit reads (:mod:`emccdcal.plugins`)."""
    return {n: t for n, t in plugins.load(plugins.TOOLS).items() if t.read is not None}


def __getattr__(name):
    if name == "TOOL_NAMES":  # the tools an audit reads: --tool's name → the tool's own
        return {n: t.title for n, t in _readable().items()}
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

#: What a field can stand for: the calibrated quantity, its unit, how to say it.
_QUANTITIES = {
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
    it stands for (a key of ``_QUANTITIES``, or ``"qe"``, or None: not comparable)."""

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
        out = [f"{_readable()[r.tool].title}: {comment(r.where)} "
               f"(set-point {format_setpoint(self.setpoint)}x)"]
        width = max(len(row["field"]) for row in self.rows)
        for row in self.rows:
            out.append(f"  {comment(row['field']):<{width}}  {comment(row['text'])}")
        out.append(f"  photons: {r.formula} = {r.pe_per_adu:.6g} e-/ADU against the "
                   f"calibrated phi/g = {self.calibrated_pe_per_adu:.6g}: "
                   f"{100 * self.photon_bias:+.2f} %")
        verdict = "OK" if self.ok else "OFF"
        out.append(f"  {verdict}: " + ("; ".join(self.problems) if self.problems else
                   f"photons within {100 * self.tolerance:g} %, baseline within "
                   f"{self.offset_tolerance:.3g} ADU"))
        return out


# --------------------------------------------------------------------------------------
# Reading the tools' files
# --------------------------------------------------------------------------------------
def _number(value, what, path):
    if isinstance(value, bool):  # YAML's true is not 1
        raise InputError(f"'{path}': {what} is {value!r}, not a number")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise InputError(f"'{path}': {what} is {value!r}, not a number") from None
    if not math.isfinite(x):
        raise InputError(f"'{path}': {what} is {value!r}, not a finite number")
    return x


def _positive(value, what, path):
    x = _number(value, what, path)
    if x <= 0:
        raise InputError(f"'{path}': {what} is {value!r}; it must be > 0")
    return x


def _qe(value, what, path):
    """A quantum efficiency: a number in (0, 1] (a percentage or a sign error refused)."""
    x = _number(value, what, path)
    if not 0 < x <= 1:
        raise InputError(f"'{path}': {what} is {value!r}; a quantum efficiency lies in "
                         "(0, 1]")
    return x


def _leaves(tree, path=()):
    """(keys, value) of every non-mapping leaf of nested mappings."""
    if isinstance(tree, dict):
        for key, value in tree.items():
            yield from _leaves(value, (*path, str(key)))
    else:
        yield path, tree


def _picasso_qe(value, name, path):
    """Picasso's QE: a number, or a table by wavelength (each value checked; one value
    is the QE, several leave it to the wavelength the user picks: None)."""
    if value is None:
        return None
    if isinstance(value, dict):
        values = [_qe(v, f"{name}: Quantum Efficiency at {k}", path) for k, v in value.items()]
        return values[0] if len(values) == 1 else None
    return _qe(value, f"{name}: Quantum Efficiency", path)


def _picasso(doc, path, setpoint, tool_gain):
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
            gain, gain_note = _positive(cam[gain_key], f"{name}: {gain_key}", path), ""
        else:
            gain, gain_note = float(setpoint), ("not in the file: the set-point, as typed "
                                                "into Picasso's EM gain box")
        baseline = (_number(cam["Baseline"], f"{name}: Baseline", path)
                    if "Baseline" in cam else None)
        qe = _picasso_qe(cam.get("Quantum Efficiency"), name, path)
        for keys, value in _leaves(cam["Sensitivity"]):
            where = " > ".join(("Cameras", str(name), "Sensitivity", *keys))
            sens = _positive(value, where, path)
            fields = [Field("Sensitivity", sens, "e_per_adu"),
                      Field(gain_key or "EM gain", gain, "em_gain", gain_note)]
            if baseline is not None:
                fields.insert(0, Field("Baseline", baseline, "offset"))
            readings.append(Reading("picasso", where, tuple(fields), sens / gain,
                                    "Sensitivity / Gain", baseline, qe))
    if not readings:
        raise InputError(f"'{path}': no camera of 'Cameras' has a Sensitivity")
    return readings


def _find_tables(tree, keys, path=()):
    """(path, table) of every mapping in ``tree`` holding all of ``keys``."""
    if isinstance(tree, dict):
        if all(k in tree for k in keys):
            yield path, tree
        for key, value in tree.items():
            yield from _find_tables(value, keys, (*path, str(key)))
    elif isinstance(tree, list):
        for i, value in enumerate(tree):
            yield from _find_tables(value, keys, (*path, f"[{i}]"))


def _decode(doc, path):
    readings = []
    for where, cam in _find_tables(doc, ("e_per_adu", "em_gain")):
        name = " > ".join(where) or "Camera"
        phi = _positive(cam["e_per_adu"], f"{name}: e_per_adu", path)
        if cam["em_gain"] is None:
            gain, note = 1.0, "null: DECODE's sCMOS model, no EM gain"
        else:
            gain, note = _positive(cam["em_gain"], f"{name}: em_gain", path), ""
        fields = [Field("e_per_adu", phi, "e_per_adu"), Field("em_gain", gain, "em_gain", note)]
        baseline = None
        if "baseline" in cam:
            baseline = _number(cam["baseline"], f"{name}: baseline", path)
            fields.insert(0, Field("baseline", baseline, "offset"))
        if "read_sigma" in cam:
            fields.append(Field("read_sigma", _number(cam["read_sigma"], "read_sigma", path),
                                "read_noise_e"))
        qe = _qe(cam["qe"], f"{name}: qe", path) if cam.get("qe") is not None else None
        readings.append(Reading("decode", name, tuple(fields), phi / gain,
                                "e_per_adu / em_gain", baseline, qe))
    if not readings:
        raise InputError(f"'{path}': no table with e_per_adu and em_gain: not a DECODE "
                         "camera block")
    return readings


def _thunderstorm(text, path):
    # comments never run: /* ... */ blocks and // to the end of a line (outside strings)
    code = re.sub(r"/\*.*?\*/", " ", text, flags=re.S)
    code = "\n".join(re.sub(r'^((?:[^"/]|"[^"]*"|/(?!/))*)//.*$', r"\1", line)
                     for line in code.splitlines())
    found = re.findall(r'run\(\s*"Camera setup"\s*,\s*"([^"]*)"', code)
    if not found:
        raise InputError(f"'{path}': no run(\"Camera setup\", \"...\") line: not a "
                         "ThunderSTORM camera macro")
    if len(set(found)) > 1:  # each line sets the camera in turn: the last one holds
        raise InputError(f"'{path}': {len(found)} different Camera setup lines; the macro's "
                         "camera is ambiguous: audit a macro with one")
    options = dict(re.findall(r"(\w+)=(\S+)", found[-1]))
    options = {k.lower(): v for k, v in options.items()}
    missing = [k for k in ("offset", "photons2adu") if k not in options]
    if missing:
        raise InputError(f"'{path}': Camera setup without {', '.join(missing)}")
    phi = _positive(options["photons2adu"], "photons2adu", path)
    em = options.get("isemgain", "false").lower() == "true"
    gain = _positive(options.get("gainem", 1), "gainem", path) if em else 1.0
    baseline = _number(options["offset"], "offset", path)
    fields = (Field("offset", baseline, "offset"),
              Field("photons2adu", phi, "e_per_adu", "e-/ADU, despite its name"),
              Field("gainem", gain, "em_gain", "" if em else "isemgain=false: taken as 1"))
    qe = (_qe(options["quantumefficiency"], "quantumefficiency", path)
          if "quantumefficiency" in options else None)
    return [Reading("thunderstorm", "Camera setup", fields, phi / gain,
                    "photons2adu / gainem", baseline, qe)]


def _gdsc(doc, path):
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
    cpp = _positive(cpp, "countPerPhoton", path)
    qe = get(camera, "quantumEfficiency", "quantum_efficiency")
    qe = 1.0 if qe is None else _qe(qe, "quantumEfficiency", path)
    fields = [Field("countPerPhoton", cpp / qe, "adu_per_e_total",
                    f"QE x g/phi; divided by its QE {qe:g}")]
    baseline = get(camera, "bias")
    if baseline is not None:
        baseline = _number(baseline, "bias", path)
        fields.insert(0, Field("bias", baseline, "offset"))
    noise = get(camera, "readNoise", "read_noise")
    if noise is not None:
        fields.append(Field("readNoise", _number(noise, "readNoise", path), "read_noise"))
    return [Reading("gdsc", "Calibration", tuple(fields), qe / cpp,
                    "QE / countPerPhoton", baseline, qe)]


def _smap(doc, path):
    readings = [_smap_reading(" > ".join(where) or "camera", cam, path)
                for where, cam in _find_tables(doc, ("conversion", "emgain"))]
    if not readings:
        raise InputError(f"'{path}': no camera settings with conversion and emgain: not "
                         "SMAP's")
    return readings


def _smap_reading(name, cam: dict, path, gain_note="") -> Reading:
    """One SMAP camera (state): ``conversion`` e⁻/ADU, ``emgain``, ``offset`` ADU and
    ``EMon``, as SMAP's CameraConverter uses them."""
    phi = _positive(_scalar(cam["conversion"]), f"{name}: conversion", path)
    em = str(_scalar(cam.get("EMon", True))).strip().lower() not in ("0", "false", "0.0")
    gain = _positive(_scalar(cam["emgain"]), f"{name}: emgain", path) if em else 1.0
    fields = [Field("conversion", phi, "e_per_adu"),
              Field("emgain", gain, "em_gain", gain_note if em else "EMon false: taken as 1")]
    baseline = None
    if cam.get("offset") is not None:
        baseline = _number(_scalar(cam["offset"]), f"{name}: offset", path)
        fields.insert(0, Field("offset", baseline, "offset"))
    return Reading("smap", name, tuple(fields), phi / gain, "conversion / emgain", baseline)


def _cell_text(value) -> str:
    """A MATLAB cell's text (a char array read by SciPy), "" where empty."""
    arr = np.asarray(value)
    return "" if arr.size == 0 else str(arr.reshape(-1)[0]).strip()


def _smap_cameras(raw, path, setpoint) -> list[Reading] | None:
    """SMAP's Camera Manager database (``settings/cameras.mat``) as SMAP's
    ``getCameraCalibration`` reads it, or None where ``raw`` is not one. Each camera
    (``cameras(k)``, named by ``ID.name``) has a parameter table ``par``, one row per
    parameter: name, mode, fixed value, metadata field, –, conversion. A ``fix``
    parameter's value is in the table; a ``state dependent`` one in each state's
    ``par`` (one reading per state); a ``metadata`` one comes from the image files:
    the EM gain then is the set-point the files record."""
    cameras = raw.get("cameras")
    if cameras is None or not all(hasattr(c, "par") for c in np.asarray(cameras).reshape(-1)):
        return None
    readings = []
    for cam in np.asarray(cameras).reshape(-1):
        ids = np.asarray(getattr(cam, "ID", None)).reshape(-1)
        name = _cell_text(getattr(ids[0], "name", "camera") if ids.size else "camera")
        table = np.asarray(cam.par, dtype=object)
        if table.ndim != 2 or table.shape[1] < 3:
            raise InputError(f"'{path}': camera {name!r}: its par is not SMAP's table")
        rows = {_cell_text(table[i, 0]): i for i in range(table.shape[0])}
        states = list(np.asarray(getattr(cam, "state", [])).reshape(-1))
        wanted = [k for k in ("conversion", "emgain", "offset", "EMon") if k in rows]
        if not {"conversion", "emgain"} <= set(wanted):
            raise InputError(f"'{path}': camera {name!r} has no conversion or emgain row")
        modes = {k: _cell_text(table[rows[k], 1]) for k in wanted}
        if modes["conversion"] == "metadata":
            raise InputError(f"'{path}': camera {name!r} takes its conversion from the "
                             "image files' metadata; audit the number those files hold")
        dependent = any(m == "state dependent" for m in modes.values())
        for j, state in enumerate(states if dependent else [None]):
            values, note = {}, ""
            for k in wanted:
                if modes[k] == "fix":
                    values[k] = _cell_text(table[rows[k], 2])
                elif modes[k] == "state dependent":
                    values[k] = _cell_text(np.asarray(state.par, dtype=object)[rows[k], 1])
                elif k == "emgain":  # from the files' metadata: the set-point they record
                    values[k], note = setpoint, "from the files' metadata: the set-point"
            where = f"cameras > {name}" + ("" if state is None else f" > state {j + 1}")
            readings.append(_smap_reading(where, values, path, note))
    return readings


def _scalar(value):
    """A MATLAB value read by SciPy (an array of one element) as a Python scalar."""
    arr = np.asarray(value)
    if arr.size != 1:
        return value
    item = arr.reshape(-1)[0]
    return item.item() if hasattr(item, "item") else item


def _mat_raw(path, squeeze=False):
    """A MATLAB file's variables as SciPy reads them (structs as objects)."""
    from scipy.io import loadmat

    _files.check_mat(path)
    try:
        return loadmat(path, squeeze_me=squeeze, struct_as_record=False)
    except Exception as exc:  # noqa: BLE001 - a damaged file is one line
        raise InputError(f"'{path}': not a readable MATLAB file ({exc})") from None


def _mat_tree(path):
    """A MATLAB file as nested dicts (structs become dicts)."""
    raw = _mat_raw(path, squeeze=True)

    def convert(value, depth=0):
        if depth > 20:
            return None
        if hasattr(value, "_fieldnames"):
            return {n: convert(getattr(value, n), depth + 1) for n in value._fieldnames}
        if isinstance(value, np.ndarray) and value.dtype == object:
            return [convert(v, depth + 1) for v in value.reshape(-1)]
        return value

    return {k: convert(v) for k, v in raw.items() if not k.startswith("__")}


def _pyme(doc, path):
    flat = {}
    for keys, value in _leaves(doc):
        flat[".".join(keys)] = value
    if "Camera.ElectronsPerCount" not in flat:
        raise InputError(f"'{path}': no Camera.ElectronsPerCount: not PYME metadata")
    phi = _positive(flat["Camera.ElectronsPerCount"], "Camera.ElectronsPerCount", path)
    gain = _positive(flat.get("Camera.TrueEMGain", 1.0), "Camera.TrueEMGain", path)
    fields = [Field("Camera.ElectronsPerCount", phi, "e_per_adu"),
              Field("Camera.TrueEMGain", gain, "em_gain")]
    baseline = None
    if "Camera.ADOffset" in flat:
        baseline = _number(flat["Camera.ADOffset"], "Camera.ADOffset", path)
        fields.insert(0, Field("Camera.ADOffset", baseline, "offset"))
    if "Camera.ReadNoise" in flat:
        fields.append(Field("Camera.ReadNoise", _number(flat["Camera.ReadNoise"],
                                                        "Camera.ReadNoise", path), "read_noise_e"))
    return [Reading("pyme", "metadata", tuple(fields), phi / gain,
                    "ElectronsPerCount / TrueEMGain", baseline)]


def _pyme_md(text):
    """PYME's ``.md`` metadata (Python assignments) as a dict: numbers only, never run."""
    found = {}
    for key, value in re.findall(r"""^\s*md\[\s*['"]([\w.]+)['"]\s*\]\s*=\s*(.*?)\s*(?:#.*)?$""",
                                 text, flags=re.M):
        if not re.fullmatch(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?", value):
            value = f"{value} (an expression, never evaluated)"  # refused as not a number
        found[key] = value
    return found


def _storm_analysis(path):
    root = _files.load_xml(path, what="storm-analysis parameters file")
    values = {el.tag: el.text for el in root.iter() if el.tag in ("camera_gain", "camera_offset")}
    if "camera_gain" not in values:
        raise InputError(f"'{path}': no camera_gain: not storm-analysis parameters")
    gain = _positive(values["camera_gain"], "camera_gain", path)
    fields = [Field("camera_gain", gain, "adu_per_e_total", "g/phi, ADU per photoelectron")]
    baseline = None
    if "camera_offset" in values:
        baseline = _number(values["camera_offset"], "camera_offset", path)
        fields.insert(0, Field("camera_offset", baseline, "offset"))
    return [Reading("storm-analysis", "settings", tuple(fields), 1 / gain, "1 / camera_gain",
                    baseline)]


def _guess_tool(path: Path, text: str | None, doc) -> str:
    """The first registered tool that recognises the file as its own."""
    readable = _readable()
    for name, tool in readable.items():
        if tool.recognizes is not None and tool.recognizes(path, text, doc):
            return name
    raise InputError(f"'{path}': not a camera file of a tool emccdcal knows "
                     f"({', '.join(t.title for t in readable.values())}); give --tool NAME "
                     "if it is one")


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
    if path.suffix.lower() == ".mat":
        if tool in (None, "smap"):
            found = _smap_cameras(_mat_raw(path), path, setpoint)
            if found is not None:
                return found
        doc = _mat_tree(path)
    elif path.suffix.lower() != ".xml":
        text = _files.read_text(path, what="tool's settings file")
        doc = _parse_text(path, text)
    tool = tool or _guess_tool(path, text, doc)
    return readable[tool].read(path, text, doc, setpoint, tool_gain)


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
    truth = {k: values[k]["median"] for k in _QUANTITIES}
    # photoelectrons per ADU, from the same references as the tool's own rows: a tool
    # holding g/φ as one number (gdsc-smlm, storm-analysis) against the median over
    # pixels of g/φ, one holding φ and g against their medians, so that a file whose
    # every row agrees reads no photon bias
    combined = any(f.quantity == "adu_per_e_total" for f in reading.fields)
    pe_per_adu = (1.0 / truth["adu_per_e_total"] if combined
                  else truth["e_per_adu"] / truth["em_gain"])
    rows = []
    for f in reading.fields:
        row = {"field": f.name}
        note = f" ({f.note})" if f.note else ""
        if f.quantity == "offset":
            diff = f.value - truth["offset"]
            row["text"] = (f"{f.value:.6g} ADU; calibrated offset {truth['offset']:.6g} ADU: "
                           f"{diff:+.3g} ADU ({-diff * pe_per_adu:+.3g} e- per pixel and frame)"
                           + note)
        elif f.quantity in _QUANTITIES:
            unit, what = _QUANTITIES[f.quantity]
            rel = f.value / truth[f.quantity] - 1
            row["text"] = (f"{f.value:.6g} {unit}".rstrip() + f"; calibrated {what} "
                           f"{truth[f.quantity]:.6g}: {100 * rel:+.2f} %{note}")
        else:  # a number of the tool's that no calibrated quantity stands for alone
            row["text"] = f"{f.value:.6g} (compared only in the photons){note}"
        rows.append(row)
    if reading.qe is not None:
        text = f"{reading.qe:g}: photons = photoelectrons / {reading.qe:g}"
        if qe is not None:
            text += f"; given QE {qe:g}: {100 * (reading.qe / qe - 1):+.2f} %"
        rows.append({"field": "QE", "text": text})
    bias = reading.pe_per_adu / pe_per_adu - 1
    spread = values["offset"]["spread"] or 0.0
    tol_offset = spread + 1.0 if offset_tolerance is None else offset_tolerance
    offset_error = None if reading.baseline is None else reading.baseline - truth["offset"]
    problems = []
    if abs(bias) > tolerance:
        worst = max((f for f in reading.fields if f.quantity in ("e_per_adu", "em_gain",
                                                                  "adu_per_e_total")),
                    key=lambda f: abs(math.log(f.value / truth[f.quantity])), default=None)
        name = f" (most of it {worst.name})" if worst is not None else ""
        problems.append(f"photons {100 * bias:+.1f} %{name}, beyond {100 * tolerance:g} %: "
                        f"{reading.formula} should be {pe_per_adu:.6g} e-/ADU")
    if offset_error is not None and abs(offset_error) > tol_offset:
        base = next(f.name for f in reading.fields if f.quantity == "offset")
        problems.append(f"{base} {offset_error:+.3g} ADU from the calibrated offset "
                        f"{truth['offset']:.6g} ADU, beyond {tol_offset:.3g} ADU")
    if qe is not None and reading.qe is not None and abs(reading.qe / qe - 1) > tolerance:
        problems.append(f"QE {reading.qe:g} but {qe:g} given: photons "
                        f"{100 * (qe / reading.qe - 1):+.1f} %")
    return Audit(reading, setpoint, rows, pe_per_adu, bias, offset_error, tol_offset, tolerance,
                 problems)


def audit(toolfile, calibration, *, setpoint=None, tool=None, tool_gain=None, qe=None,
          tolerance=DEFAULT_TOLERANCE, offset_tolerance=None) -> list[Audit]:
    """Compare a localization tool's camera numbers with a calibration.

    Parameters
    ----------
    toolfile : str or Path
        The tool's file (:func:`read_tool_file`).
    calibration : Calibration, str or Path
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
    """
    if not (0 < tolerance < 1):
        raise OptionError(f"tolerance is a fraction in (0, 1); got {tolerance}")
    if qe is not None and not (0 < qe <= 1):
        raise OptionError(f"--qe is photoelectrons per photon, in (0, 1]; got {qe}")
    cal = calibration if isinstance(calibration, Calibration) else load_calibration(calibration)
    s = pick_setpoint(cal, setpoint)
    values = camera_values(cal, s)
    readings = _matching(read_tool_file(toolfile, tool=tool, setpoint=s, tool_gain=tool_gain),
                         cal.camera)
    return [_compare(r, values, s, tolerance, offset_tolerance, qe) for r in readings]


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
        wanted.append(lambda where, r=float(rate): any(
            abs(float(m) - r) < 1e-6 for m in re.findall(r"([0-9.]+)\s*MHz", where)))
    analog = camera.get("analog_gain")
    if analog is not None:
        number = re.findall(r"[0-9.]+", str(analog))
        wanted.append(lambda where, n=number: bool(n) and any(
            n[0] == m for m in re.findall(r"[Gg]ain\s*([0-9.]+)", where)))
    chosen = readings
    for w in wanted:
        narrowed = [r for r in chosen if w(r.where)]
        if narrowed:  # a setting no entry names is not a key of the table
            chosen = narrowed
    return chosen if len(chosen) == 1 else readings
