"""SMAP (its camera manager's ``cameras.mat``, or a JSON of its parameters): writer and
the audit's readers, one plug-in.
"""

from __future__ import annotations

import json
import warnings

import numpy as np

from ...errors import ExportWarning, InputError
from ...model import adc
from ...plugins import Tool
from .. import toolkit
from ..toolkit import Field, Reading


def write(cal, s, v, out, qe, pixel_size_nm, name):
    """SMAP's camera settings (``loc_cameraSettings``: ``EMon``, ``emgain``, ``conversion``
    e⁻/ADU, ``offset`` ADU), as JSON and as a Camera Manager file (``smap-cameras.mat``),
    and its camera correction file (``offsetmap`` ADU, ``gainmap`` photons per ADU = φ/g,
    ``varmap`` ADU², indexed [row, col])."""
    from scipy.io import savemat

    offset, sigma = cal.dark(s)
    prov = toolkit.provenance(cal, s, qe)
    mat = out / "smap-correction.mat"
    variance = adc.count_variance(sigma, s == 1)  # the dark counts' (σ analog where rounded)
    maps = {"offsetmap": offset, "gainmap": cal.e_per_adu / cal.gain(s), "varmap": variance}
    content = {k: np.asarray(m, dtype=np.float32) for k, m in maps.items()}
    toolkit.write_file(mat, lambda p: savemat(p, {**content, "emccdcal": json.dumps(prov)}))
    par = {
        "EMon": bool(v["em_gain"]["median"] > 1),
        "emgain": toolkit.rounded(v["em_gain"]["median"]),
        "conversion": toolkit.rounded(v["e_per_adu"]["median"]),
        "offset": toolkit.rounded(v["offset"]["median"]),
        "correctionfile": mat.stem,
        "comment": f"emccdcal {prov['emccdcal_version']} {prov['method']} "
        + " ".join(r["sha256"][:12] for r in prov["results"]),
    }
    if pixel_size_nm is not None:
        par["cam_pixelsize_um"] = toolkit.rounded(pixel_size_nm / 1000.0)
    else:
        warnings.warn(
            "SMAP's Camera Manager file holds a pixel size: SMAP's default "
            "0.1 µm is written; give --pixel-size NM, or set it in the Camera "
            "Manager",
            stacklevel=3,
            category=ExportWarning,
        )
    doc = {"loc_cameraSettings": par, "emccdcal": prov}
    cameras = out / "smap-cameras.mat"
    toolkit.write_file(cameras, lambda p: savemat(p, _smap_camera_manager(par)))
    return [
        toolkit.write_text(out / "smap-camera.json", json.dumps(doc, indent=2) + "\n"),
        mat,
        cameras,
    ]


#: SMAP's Camera Manager parameter table (``CameraManager.m``, ``intpartable``): name,
#: mode, value of a new camera, conversion SMAP applies to the text. Rows SMAP reads from
#: the image files ("metadata") are left to them; the others are fixed to our numbers.
_SMAP_TABLE = (
    ("EMon", "fix", "1", "str2double(X)"),
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
    ("imagemetadata", "fix", "", ""),
)


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

    values = {
        key: text(key, par[key]) if key in par else default for key, _, default, _ in _SMAP_TABLE
    }
    cells = lambda rows: np.array(rows, dtype=object)  # noqa: E731 - MATLAB cell arrays
    table = cells(
        [
            [key, mode, values[key], "select", "", conversion, ""]
            for key, mode, _, conversion in _SMAP_TABLE
        ]
    )
    state = {
        "statelist": cells([["State 1"]]),
        "defpar": cells([["select", ""]]),
        "par": cells([[key, values[key]] for key, *_ in _SMAP_TABLE]),
    }
    entry = {"ID": {"name": "Default", "tag": "select", "value": ""}, "par": table, "state": state}
    return {"cameras": entry, "camtab": cells([["Default", "select", ""]])}


def _read_doc(doc, path):
    readings = [
        _smap_reading(" > ".join(where) or "camera", cam, path)
        for where, cam in toolkit.find_tables(doc, ("conversion", "emgain"))
    ]
    if not readings:
        raise InputError(f"'{path}': no camera settings with conversion and emgain: not SMAP's")
    return readings


def _smap_reading(name, cam: dict, path, gain_note="") -> Reading:
    """One SMAP camera (state): ``conversion`` e⁻/ADU, ``emgain``, ``offset`` ADU and
    ``EMon``, as SMAP's CameraConverter uses them."""
    phi = toolkit.positive(toolkit.mat_scalar(cam["conversion"]), f"{name}: conversion", path)
    em = str(toolkit.mat_scalar(cam.get("EMon", True))).strip().lower() not in ("0", "false", "0.0")
    gain = (
        toolkit.positive(toolkit.mat_scalar(cam["emgain"]), f"{name}: emgain", path) if em else 1.0
    )
    fields = [
        Field("conversion", phi, "e_per_adu"),
        Field("emgain", gain, "em_gain", gain_note if em else "EMon false: taken as 1"),
    ]
    baseline = None
    if cam.get("offset") is not None:
        baseline = toolkit.number(toolkit.mat_scalar(cam["offset"]), f"{name}: offset", path)
        fields.insert(0, Field("offset", baseline, "offset"))
    return Reading("smap", name, tuple(fields), phi / gain, "conversion / emgain", baseline)


def _cell_text(value) -> str:
    """A MATLAB cell's text (a char array read by SciPy), "" where empty."""
    arr = np.asarray(value)
    return "" if arr.size == 0 else str(arr.reshape(-1)[0]).strip()


def _read_mat(path, setpoint):
    """SMAP's camera correction file (per pixel) or its Camera Manager's ``cameras.mat``;
    None for another file."""
    if path.suffix.lower() != ".mat":
        return None
    raw = toolkit.mat_raw(path)
    if all(k in raw for k in ("offsetmap", "gainmap", "varmap")):
        return _smap_correction(raw, path)
    return _smap_cameras(raw, path, setpoint)


def _smap_correction(raw, path) -> list[Reading]:
    """SMAP's camera correction file: ``offsetmap`` (ADU), ``gainmap`` (photons per ADU,
    φ/g) and ``varmap`` (ADU²), [row, col], read as per-pixel maps (no sensor origin: the
    maps are taken to be the calibration's pixels)."""
    maps = {k: np.asarray(raw[k], dtype=float) for k in ("offsetmap", "gainmap", "varmap")}
    with np.errstate(divide="ignore", invalid="ignore"):
        total = 1.0 / maps["gainmap"]  # gainmap is photons per ADU
    per_pixel = {"offset": maps["offsetmap"], "adu_per_e_total": total, "variance": maps["varmap"]}
    return toolkit.per_pixel_reading(
        "smap", "camera correction", path, per_pixel, names=("offsetmap", "1/gainmap"),
        gain_note="ADU per e-", formula="gainmap (median)",
    )  # fmt: skip


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
            raise InputError(
                f"'{path}': camera {name!r} takes its conversion from the "
                "image files' metadata; audit the number those files hold"
            )
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


TOOL = Tool(
    "smap",
    "SMAP",
    write,
    lambda path, text, doc, setpoint, tool_gain: _read_doc(doc, path),
    lambda path, text, doc: (
        path.suffix.lower() == ".mat"
        or (
            isinstance(doc, dict)
            and next(toolkit.find_tables(doc, ("conversion", "emgain")), None) is not None
        )
    ),
    read_file=lambda path, setpoint: _read_mat(path, setpoint),
)
