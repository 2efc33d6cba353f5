"""The calibration result: an xarray dataset, its files, and their summary.

Every calibration method ends here. :func:`make_dataset` labels the per-pixel estimates
(dimensions, coordinates, units), :func:`save` writes ``OUT/calibration.nc`` and
``OUT/summary.json`` atomically, :func:`load` reads a result back and checks that it is
one, and :func:`summarize` reduces it to per-parameter statistics over pixels.
``docs/results.md`` describes the files for users.

Dimensions and variables (``R`` rows, ``C`` columns)
----------------------------------------------------
==============================  ===============================  ========
variable (each with ``_se``)    dims                             units
==============================  ===============================  ========
``e_per_adu``                   (row, col)                       e-/ADU
``adu_per_e``                   (row, col)                       ADU/e-
``em_gain``                     (setpoint, row, col)             1
``photoelectrons``              (row, col) or (D, row, col) [*]  e-
==============================  ===============================  ========

[*] ``D`` is ``level`` or ``setpoint``, see below. Without ``_se``: ``loglik`` (row, col)
in nat, and ``converged`` (row, col), bool, units "1".

Coordinates: ``row`` and ``col`` (sensor pixel indices, integers; ``origin`` shifts them
for a tile of a larger sensor), ``setpoint`` (the camera's EM-gain set-points, float, in the
order given) and ``level`` (illumination-level labels, str).

Which dims ``photoelectrons`` gets
----------------------------------
Pass ``photoelectrons_dims`` to say it outright. Otherwise the rule is:

* a 2-D array is ``(row, col)`` — one intensity shared by all acquisitions (``gs``);
* a 3-D array is ``(level, row, col)`` if ``levels`` is given and ``setpoints`` is not,
  ``(setpoint, row, col)`` if ``setpoints`` is given and ``levels`` is not;
* anything else (both given, neither given, other ranks) needs ``photoelectrons_dims``.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import re
import time
import warnings
from dataclasses import dataclass, field
from numbers import Number
from pathlib import Path

import numpy as np
import xarray as xr

from . import defaults, identity
from ._output import file_sha256, read_netcdf, write_netcdf
from ._util import finite_or_none, format_setpoint, one_line  # noqa: F401 - re-exported
from .errors import FitWarning, InputError, InputWarning, MissingFileError, OptionError
from .errors import issue_once_per_kind

__all__ = [
    "UNITS",
    "LONG_NAMES",
    "REQUIRED_VARIABLES",
    "CALIBRATION_FILE",
    "SUMMARY_FILE",
    "make_dataset",
    "save",
    "load",
    "summarize",
    "format_setpoint",
    "run_recorded",
    "Calibration",
    "load_calibration",
    "pixel_statistics",
    "IDENTITY_FIELDS",
    "camera_of",
    "result_files",
]

CALIBRATION_FILE = "calibration.nc"
SUMMARY_FILE = "summary.json"

#: ``units`` attribute of every standard variable and coordinate (ASCII; "1" is
#: dimensionless, "nat" the natural-log unit of a log-likelihood).
UNITS = {
    "e_per_adu": "e-/ADU",
    "adu_per_e": "ADU/e-",
    "em_gain": "1",
    "photoelectrons": "e-",
    "loglik": "nat",
    "converged": "1",
    "offset": "ADU",
    "read_noise": "ADU",
    "setpoint": "1",
    "level": "1",
    "row": "pixel",
    "col": "pixel",
}

LONG_NAMES = {
    "e_per_adu": "ADU conversion factor phi (photoelectrons per ADU count)",
    "adu_per_e": "inverse ADU conversion factor 1/phi (ADU counts per photoelectron)",
    "em_gain": "true mean EM gain g at each gain set-point",
    "photoelectrons": "mean photoelectrons E per pixel per frame",
    "loglik": "maximised log-likelihood (natural log) of the pixel's data",
    "converged": "fit converged (estimates usable)",
    "offset": "offset S0",
    "read_noise": "read-noise standard deviation sigma",
    "setpoint": "EM gain set-point of the camera",
    "level": "illumination level label",
    "row": "sensor row index",
    "col": "sensor column index",
}

#: Variables every result file must hold (``em_gain`` only where there are set-points).
REQUIRED_VARIABLES = (
    "e_per_adu",
    "e_per_adu_se",
    "photoelectrons",
    "photoelectrons_se",
    "loglik",
    "converged",
)

_UNITS_NOTE = (
    "e_per_adu is phi in photoelectrons per ADU count (e-/ADU), adu_per_e = 1/e_per_adu; "
    "em_gain is dimensionless (1 = no multiplication); photoelectrons in e- per pixel per "
    "frame; offset and read_noise in ADU; loglik in nats; every <name>_se is the standard "
    "error of <name>, in the units of <name>"
)
_RESERVED_ATTRS = (
    "method",
    "emccdcal_version",
    "manifest_sha256",
    "manifest_path",
    "created",
    "units_note",
)
_PIXEL_DIMS = ("row", "col")
_HEX64 = re.compile(r"^[0-9a-f]{64}$")


def em_model_summary(ds) -> dict:
    """The EM register model a result was fitted with: ``{"em_model": ..., and for the
    cascade "register_stages": N}``; empty for results without one (mean–variance)."""
    from .model.noise import EMModel

    model = EMModel.from_attrs(ds.attrs)
    return {} if model is None else model.attrs


def _package_version() -> str:
    from . import __version__

    return __version__


def _major(version: str) -> int | None:
    m = re.match(r"\s*(\d+)", str(version))
    return int(m.group(1)) if m else None


# --------------------------------------------------------------------------------------
# make_dataset
# --------------------------------------------------------------------------------------
def _attr_value(key, value):
    """NetCDF-storable version of an attribute value (bool -> int), or ValueError."""
    if isinstance(value, (bool, np.bool_)):
        return int(value)
    if isinstance(value, (str, Number, np.number)):
        return value
    if isinstance(value, (list, tuple, np.ndarray)):
        items = list(np.asarray(value).ravel()) if isinstance(value, np.ndarray) else list(value)
        if all(isinstance(v, (str, Number, np.number)) and not isinstance(v, bool) for v in items):
            return value
    raise ValueError(
        f"dataset attribute {key!r} must be a str, a number, or a list of them; "
        f"got {type(value).__name__}"
    )


def make_dataset(
    *,
    method: str,
    setpoints=None,
    levels=None,
    e_per_adu,
    e_per_adu_se,
    em_gain=None,
    em_gain_se=None,
    photoelectrons,
    photoelectrons_se,
    loglik=None,
    converged,
    manifest_hash: str,
    manifest_path=None,
    extra: dict | None = None,
    attrs: dict | None = None,
    photoelectrons_dims: tuple[str, ...] | None = None,
    origin: tuple[int, int] = (0, 0),
) -> xr.Dataset:
    """Label a calibration's per-pixel estimates as an xarray dataset.

    The pixel grid ``(R, C)`` is taken from the last two axes of ``photoelectrons``.

    Parameters
    ----------
    method : str
        The calibration method (``"gs"``, ``"mv-adu"``, ...).
    setpoints : sequence of float, optional
        EM-gain set-points (dimensionless, positive, distinct): the ``setpoint`` coordinate.
        Required with ``em_gain``.
    levels : sequence of str, optional
        Illumination-level labels (distinct): the ``level`` coordinate.
    e_per_adu, e_per_adu_se : array_like, shape (R, C), or scalar
        φ and its standard error (e⁻/ADU). A scalar is broadcast (e.g. a fixed φ with SE 0).
    em_gain, em_gain_se : array_like, shape (S, R, C), optional
        True EM gain per set-point and its SE (dimensionless). Where a set-point is 1 the
        gain must be 1 (or NaN) and its SE 0 (or NaN): 1× means no multiplication.
    photoelectrons, photoelectrons_se : array_like
        E and its SE (e⁻ per pixel per frame); dims by ``photoelectrons_dims`` or the rule
        in the module docstring.
    loglik : array_like, shape (R, C), optional
        Maximised log-likelihood per pixel (nats). Absent (e.g. mean–variance) → NaN.
    converged : array_like of bool, shape (R, C), or scalar
        Whether each pixel's fit converged.
    manifest_hash : str
        SHA-256 of the manifest file's bytes, 64 hex digits.
    manifest_path : str or Path, optional
        Where the manifest was (stored as text; "" when not given).
    extra : dict, optional
        Method-specific variables, ``name -> (dims, array, units)`` or
        ``(dims, array, units, long_name)``, e.g.
        ``{"offset": (("setpoint", "row", "col"), s0, "ADU")}``. Known dims must have
        their sizes; names must not clash with the standard variables.
    attrs : dict, optional
        Further dataset attributes (str, numbers or lists of them; bool becomes 0/1). May
        not replace the standard ones.
    photoelectrons_dims : tuple of str, optional
        Dims of ``photoelectrons`` outright, ending in ``("row", "col")``.
    origin : (int, int), optional
        Sensor index of pixel (0, 0) of these arrays, for a tile of a larger sensor; the
        ``row``/``col`` coordinates start there. Default (0, 0).

    Returns
    -------
    xarray.Dataset
        With the variables, coordinates and attributes of the module docstring, plus
        ``adu_per_e`` and ``adu_per_e_se`` derived from φ.

    Raises
    ------
    ValueError
        Any shape that does not fit the pixel grid and the coordinates, duplicate
        set-points or levels, an ``em_gain`` without ``setpoints``, a 1× gain that is not
        1, a malformed ``manifest_hash``, an unusable attribute, or ambiguous
        ``photoelectrons`` dims.

    Examples
    --------
    >>> import numpy as np
    >>> ds = make_dataset(
    ...     method="mv-adu", levels=["L1", "L2"],
    ...     e_per_adu=np.full((2, 3), 3.8), e_per_adu_se=0.05,
    ...     photoelectrons=np.full((2, 2, 3), 100.0), photoelectrons_se=2.0,
    ...     converged=True, manifest_hash="0" * 64)
    >>> ds.photoelectrons.dims, ds.e_per_adu.attrs["units"]
    (('level', 'row', 'col'), 'e-/ADU')
    """
    if not isinstance(method, str) or not method:
        raise ValueError("method must be a non-empty string")
    if not isinstance(manifest_hash, str) or not _HEX64.match(manifest_hash.lower()):
        raise ValueError(
            f"manifest_hash must be the SHA-256 hex digest (64 hex digits); got {manifest_hash!r}"
        )
    coords = _labels(setpoints, levels)
    E = np.asarray(photoelectrons, dtype=float)
    e_dims = _photoelectron_dims(E, photoelectrons_dims, coords)
    R, C = E.shape[-2:]
    sizes = {**{k: len(v) for k, v in coords.items()}, "row": R, "col": C}

    def full(value, dims):  # a number fills its dims; an array is xarray's to check
        arr = np.asarray(value, dtype=float)
        return np.full([sizes[d] for d in dims], float(arr)) if arr.ndim == 0 else arr

    pix = _PIXEL_DIMS
    phi, phi_se = full(e_per_adu, pix), full(e_per_adu_se, pix)
    variables: dict[str, tuple[tuple[str, ...], np.ndarray]] = {
        "e_per_adu": (pix, phi),
        "e_per_adu_se": (pix, phi_se),
    }
    if em_gain is not None or em_gain_se is not None:
        if em_gain is None or em_gain_se is None:
            raise ValueError("em_gain and em_gain_se must be given together")
        if setpoints is None:
            raise ValueError("em_gain needs setpoints (the setpoint coordinate)")
        g_dims = ("setpoint",) + pix
        variables["em_gain"] = (g_dims, full(em_gain, g_dims))
        variables["em_gain_se"] = (g_dims, full(em_gain_se, g_dims))
    variables["photoelectrons"] = (e_dims, E)
    variables["photoelectrons_se"] = (e_dims, full(photoelectrons_se, e_dims))
    variables["loglik"] = (pix, full(np.nan if loglik is None else loglik, pix))
    conv = np.asarray(converged)
    if conv.dtype != bool:
        if conv.dtype.kind not in "iuf" or not np.all(np.isin(conv, (0, 1))):
            raise ValueError("converged must be boolean (or 0/1)")
        conv = conv.astype(bool)
    variables["converged"] = (pix, np.full((R, C), bool(conv)) if conv.ndim == 0 else conv)
    labelled = {name: (dims, arr, _variable_attrs(name)) for name, (dims, arr) in variables.items()}
    labelled.update(_extra_variables(extra, set(variables)))
    r0, c0 = (int(v) for v in origin)
    coords = {"row": np.arange(r0, r0 + R), "col": np.arange(c0, c0 + C), **coords}
    try:  # xarray checks that every variable's shape fits its dims and the others
        ds = xr.Dataset(
            labelled,
            coords={
                name: (name, values, {"units": UNITS[name], "long_name": LONG_NAMES[name]})
                for name, values in coords.items()
            },
            attrs=_dataset_attrs(method, manifest_hash, manifest_path, attrs),
        )
    except ValueError as exc:
        raise ValueError(f"make_dataset: {one_line(exc)}") from exc
    with np.errstate(divide="ignore", invalid="ignore"):
        ds = ds.assign(
            adu_per_e=(pix, 1.0 / phi, _variable_attrs("adu_per_e")),
            adu_per_e_se=(pix, phi_se / phi**2, _variable_attrs("adu_per_e_se")),
        )
    if "em_gain" in ds and 1.0 in ds["setpoint"].values:  # 1x: no multiplication
        g1, s1 = ds["em_gain"].sel(setpoint=1.0), ds["em_gain_se"].sel(setpoint=1.0)
        if not (np.all(np.isnan(g1) | (g1 == 1.0)) and np.all(np.isnan(s1) | (s1 == 0.0))):
            raise ValueError(
                "em_gain at set-point 1 must be 1 with standard error 0 (no multiplication)"
            )
    impossible, first = _impossible(ds)
    if impossible.any():  # never a result that its own readers would refuse
        ds["converged"].values[impossible] = False
        warnings.warn(
            f"{int(impossible.sum())} pixel(s) fitted to values no calibration can "
            f"have ({first}) are marked not converged",
            stacklevel=2,
            category=FitWarning,
        )
    return ds


def _labels(setpoints, levels) -> dict:
    """The ``setpoint`` and ``level`` coordinates that are given, checked."""
    coords: dict = {}
    if setpoints is not None:
        sp = np.asarray(setpoints, dtype=float).ravel()
        if sp.size == 0 or not np.all(np.isfinite(sp) & (sp > 0)):
            raise ValueError("setpoints must be one or more positive finite numbers")
        if np.unique(sp).size != sp.size:
            raise ValueError(f"setpoints must be distinct; got {sp.tolist()}")
        coords["setpoint"] = sp
    if levels is not None:
        lv = [str(v) for v in (levels if not isinstance(levels, str) else [levels])]
        if not lv:
            raise ValueError("levels must hold at least one label")
        if len(set(lv)) != len(lv):
            raise ValueError(f"level labels must be distinct; got {lv}")
        coords["level"] = np.array(lv, dtype=str)
    return coords


def _photoelectron_dims(E, given, coords) -> tuple[str, ...]:
    """The dims of ``photoelectrons``: given, or (row, col) with the one label given."""
    if E.ndim < 2:
        raise ValueError(f"photoelectrons must be at least 2-D (row, col); got shape {E.shape}")
    if given is not None:
        dims = tuple(given)
        if dims[-2:] != _PIXEL_DIMS or len(set(dims)) != len(dims):
            raise ValueError(f"photoelectrons_dims must end in ('row', 'col'); got {dims}")
        unknown = [d for d in dims[:-2] if d not in coords]
        if unknown:
            raise ValueError(
                f"photoelectrons_dims names {unknown}, which need the matching "
                "setpoints/levels argument"
            )
        return dims
    if E.ndim == 2:
        return _PIXEL_DIMS
    if E.ndim == 3 and len(coords) == 1:
        return tuple(coords) + _PIXEL_DIMS
    given_text = {k: "given" if k in coords else "not given" for k in ("setpoint", "level")}
    raise ValueError(
        f"cannot tell the dims of photoelectrons with shape {E.shape} (setpoints "
        f"{given_text['setpoint']}, levels {given_text['level']}); pass "
        "photoelectrons_dims"
    )


def _variable_attrs(name, units=None, long_name=None) -> dict:
    """``units`` and ``long_name`` of a variable: the names table's unless given."""
    base = name.removesuffix("_se")
    if long_name is None:
        long_name = (
            ("standard error of " + LONG_NAMES[base]) if name.endswith("_se") else LONG_NAMES[name]
        )
    return {"units": UNITS[base] if units is None else units, "long_name": long_name}


def _extra_variables(extra, standard) -> dict:
    """A method's own variables, ``name -> (dims, array, units[, long_name])``."""
    reserved = (
        (set(UNITS) - {"offset", "read_noise"})
        | standard
        | {f"{v}_se" for v in ("e_per_adu", "adu_per_e", "em_gain", "photoelectrons")}
    )
    out = {}
    for name, spec in (extra or {}).items():
        if name in reserved:
            raise ValueError(
                f"extra variable {name!r} clashes with a standard variable or coordinate"
            )
        if not isinstance(spec, tuple) or len(spec) not in (3, 4):
            raise ValueError(f"extra[{name!r}] must be (dims, array, units[, long_name])")
        if not isinstance(spec[2], str):
            raise ValueError(f"extra[{name!r}]: units must be a string")
        dims = (spec[0],) if isinstance(spec[0], str) else tuple(spec[0])
        if len(spec) == 4:
            long_name = str(spec[3])
        elif name in LONG_NAMES or (name.endswith("_se") and name[:-3] in LONG_NAMES):
            long_name = None
        else:
            long_name = name.replace("_", " ")
        out[name] = (dims, np.asarray(spec[1]), _variable_attrs(name, spec[2], long_name))
    return out


def _dataset_attrs(method, manifest_hash, manifest_path, attrs) -> dict:
    """The standard attributes of a result, then the caller's (which may not replace
    them)."""
    out = {
        "method": method,
        "emccdcal_version": _package_version(),
        "manifest_sha256": manifest_hash.lower(),
        "manifest_path": "" if manifest_path is None else str(manifest_path),
        "created": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "units_note": _UNITS_NOTE,
    }
    for key, value in (attrs or {}).items():
        if key in _RESERVED_ATTRS:
            raise ValueError(f"attribute {key!r} is set by emccdcal and cannot be replaced")
        out[key] = _attr_value(key, value)
    return out


# --------------------------------------------------------------------------------------
# summarize
# --------------------------------------------------------------------------------------
def _stats(values, se=None) -> dict:
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    out = {
        "n": int(v.size),
        "mean": finite_or_none(v.mean()) if v.size else None,
        "sd": finite_or_none(v.std(ddof=1)) if v.size > 1 else None,
        "median": finite_or_none(np.median(v)) if v.size else None,
    }
    if se is not None:
        s = np.asarray(se, dtype=float)
        s = s[np.isfinite(s)]
        out["se_median"] = finite_or_none(np.median(s)) if s.size else None
    return out


def _coord_key(ds, dim, i):
    if dim in ds.coords:
        value = ds[dim].values[i]
        return format_setpoint(value) if dim == "setpoint" else str(value)
    return str(i)


def _nested_stats(ds, da, se, mask):
    """Stats over the pixels of ``mask``, nested as ``by_<dim>`` over other dims."""
    other = [d for d in da.dims if d not in _PIXEL_DIMS]
    if not other:
        return _stats(da.values[mask], None if se is None else se.values[mask])
    dim = other[0]
    out = {}
    for i in range(da.sizes[dim]):
        out[_coord_key(ds, dim, i)] = _nested_stats(
            ds, da.isel({dim: i}), None if se is None else se.isel({dim: i}), mask
        )
    return {f"by_{dim}": out}


def summarize(ds: xr.Dataset, seconds: float | None = None) -> dict:
    """Aggregate a result over pixels, as written to ``summary.json``.

    Statistics use the **converged pixels only** and, of those, the finite values: the
    count used is ``n`` in each entry. ``sd`` has ``ddof=1``; ``se_median`` is the median
    standard error (from ``<name>_se``) over the same pixels. Parameters with dims besides
    (row, col) are nested under ``by_setpoint`` / ``by_level`` with keys from the
    coordinate (set-points formatted by :func:`format_setpoint`: ``"5"``, not ``"5.0"``).

    Parameters
    ----------
    ds : xarray.Dataset
        A result from :func:`make_dataset` or :func:`load`.
    seconds : float, optional
        Wall time of the calibration (s), recorded as ``seconds`` (null when not given).

    Returns
    -------
    dict
        JSON-serialisable: ``method``, ``emccdcal_version``, ``manifest_sha256``,
        ``manifest_path``, ``created``, ``seconds``, ``pixels`` (``total``, ``converged``,
        ``rows``, ``cols``), ``statistics_over``, and ``parameters`` mapping each variable
        name (not the ``_se``, ``_lower`` and ``_upper`` ones, not ``converged``) to
        ``units`` and its statistics.
        Non-finite numbers become null.
    """
    conv = ds["converged"].transpose("row", "col").values.astype(bool)
    params = {}
    for key, da in ds.data_vars.items():
        name = str(key)
        # Standard errors and interval bounds belong to a parameter, not beside it (an
        # average of bounds that may be infinite says nothing).
        if (
            name == "converged"
            or name.endswith(("_se", "_lower", "_upper"))
            or da.dtype.kind not in "iuf"
        ):
            continue
        if not set(_PIXEL_DIMS) <= set(da.dims):
            continue
        order = [d for d in da.dims if d not in _PIXEL_DIMS] + list(_PIXEL_DIMS)
        da = da.transpose(*order)
        se = ds[name + "_se"].transpose(*order) if name + "_se" in ds else None
        entry = {"units": da.attrs.get("units", "")}
        entry.update(_nested_stats(ds, da, se, conv))
        params[name] = entry
    return {
        "method": str(ds.attrs.get("method", "")),
        **em_model_summary(ds),
        "emccdcal_version": str(ds.attrs.get("emccdcal_version", "")),
        "manifest_sha256": str(ds.attrs.get("manifest_sha256", "")),
        "manifest_path": str(ds.attrs.get("manifest_path", "")),
        "created": str(ds.attrs.get("created", "")),
        "seconds": None if seconds is None else finite_or_none(seconds),
        "pixels": {
            "total": int(conv.size),
            "converged": int(conv.sum()),
            "rows": int(ds.sizes["row"]),
            "cols": int(ds.sizes["col"]),
        },
        "statistics_over": "converged pixels only (finite values)",
        "standard_errors": str(ds.attrs.get("standard_errors", "")),
        "parameters": params,
        "warnings": [str(w) for w in np.atleast_1d(ds.attrs.get("warnings", []))],
        "quality": json.loads(ds.attrs["quality"]) if "quality" in ds.attrs else None,
    }


def verdict_line(ds: xr.Dataset) -> str:
    """The one line that says whether a calibration stands (or stands once a check is
    made), or why it is doubtful and what to check (``ds.attrs["verdict"]``, with its
    number of warnings).

    >>> import xarray as xr
    >>> verdict_line(xr.Dataset(attrs={"verdict": "stands", "warnings": ["a", "b"]}))
    'verdict: the calibration stands; 2 warnings, each saying what it changes'
    """
    verdict = str(ds.attrs.get("verdict", "stands"))
    n = len(np.atleast_1d(ds.attrs.get("warnings", [])))
    if is_doubtful(ds):
        return f"verdict: the calibration is {verdict}"
    return f"verdict: the calibration {verdict}" + (
        f"; {n} warning{'s' * (n != 1)}, each saying what it changes" if n else ""
    )


def is_doubtful(ds: xr.Dataset) -> bool:
    """Whether a result's verdict is "doubtful" (the command line then exits 1)."""
    return str(ds.attrs.get("verdict", "stands")).startswith("doubtful")


# --------------------------------------------------------------------------------------
# save / load
# --------------------------------------------------------------------------------------
def run_recorded(build, out=None) -> xr.Dataset:
    """Build a result, recording its warnings and wall time in it; save it if asked.

    Every warning issued while ``build()`` runs goes, each once, into
    ``ds.attrs["warnings"]`` and is issued again to the caller, at most one of each kind
    (:func:`emccdcal.errors.issue_once_per_kind`); the wall time (s) goes into
    ``ds.attrs["seconds"]``. With ``out`` the result is written by :func:`save`.
    """
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = build()
    issue_once_per_kind(caught)
    ds.attrs["warnings"] = list(dict.fromkeys(str(w.message) for w in caught))
    seconds = time.perf_counter() - t0
    ds.attrs["seconds"] = seconds
    if out is not None:
        save(ds, out, seconds=seconds)
    return ds


def save(ds: xr.Dataset, out_dir, *, seconds: float | None = None, stale=()) -> dict[str, Path]:
    """Write ``calibration.nc`` and ``summary.json`` into ``out_dir`` as one set.

    Both are written to temporary files in ``out_dir`` first; only then is each renamed
    over its earlier version (:func:`emccdcal.runstore.publish`), so a reader never sees
    a half-written file and an interrupted write leaves the earlier result intact. The NetCDF file is NetCDF4/HDF5 through
    xarray's ``h5netcdf`` engine.

    Parameters
    ----------
    ds : xarray.Dataset
        A result from :func:`make_dataset`.
    out_dir : str or Path
        Output directory; created (with parents) if missing.
    seconds : float, optional
        Wall time of the calibration (s), for the summary.
    stale : sequence of str
        Files of an earlier result in ``out_dir`` to remove once the new one is in place
        (``calibrate`` names its ``report.html``).

    Returns
    -------
    dict of str to Path
        ``{"calibration": OUT/calibration.nc, "summary": OUT/summary.json}``.

    Notes
    -----
    ``converged`` is stored as an 8-bit integer with the attribute ``dtype = "bool"``;
    xarray (and :func:`load`) read it back as bool. Other NetCDF readers see 0/1.
    """
    from .runstore import publish

    summary = summarize(ds, seconds=seconds)
    text = json.dumps(summary, indent=2, allow_nan=False) + "\n"
    written = publish(
        out_dir,
        {
            CALIBRATION_FILE: lambda p: write_netcdf(ds, p),
            SUMMARY_FILE: lambda p: Path(p).write_text(text, encoding="utf-8"),
        },
        stale=stale,
    )
    # the result in memory knows its file, as one read from it does: a calibration made
    # from it records the same provenance (load_calibration)
    ds.encoding["source"] = str(written[CALIBRATION_FILE])
    ds.encoding["sha256"] = file_sha256(written[CALIBRATION_FILE])
    return {"calibration": written[CALIBRATION_FILE], "summary": written[SUMMARY_FILE]}


def _impossible(ds: xr.Dataset):
    """Converged pixels whose estimates no calibration can have (φ, gains or read noise
    not positive and finite, an offset not finite, a negative standard error): a (row,
    col) mask, and the first such value described (None where there is none)."""
    ok = np.asarray(ds["converged"].values).astype(bool)
    mask, first = np.zeros_like(ok), None

    def where_bad(name, rule):
        nonlocal mask, first
        da = ds[name]
        if not {"row", "col"} <= set(da.dims):
            return
        values = da.transpose(..., "row", "col").values.astype(float)
        if name == "em_gain":  # 1x has no multiplication: its gain may be left NaN
            one = np.asarray(ds["setpoint"].values, dtype=float) == 1.0
            values = values.copy()
            values[one] = np.where(np.isnan(values[one]), 1.0, values[one])
        with np.errstate(invalid="ignore"):
            wrong = ~rule(values) & ok
        if wrong.any():
            mask |= wrong.reshape(-1, *ok.shape).any(axis=0)
            if first is None:
                at = np.argwhere(wrong)[0]
                first = (
                    f"{name} is {values[tuple(at)]!r} at index "
                    f"{tuple(int(i) for i in at)} of a converged pixel"
                )

    def positive(v):
        return np.isfinite(v) & (v > 0)

    rules = {
        "e_per_adu": positive,
        "em_gain": positive,
        "read_noise": positive,
        "offset": np.isfinite,
    }
    for name in ds.data_vars:
        name = str(name)
        rule = rules.get(name) or (
            (lambda v: np.isnan(v) | (v >= 0)) if name.endswith("_se") else None
        )
        if rule is not None:
            where_bad(name, rule)
    return mask, first


def _check_domain(ds: xr.Dataset, p: Path) -> None:
    """The rules every result obeys, checked once for every reader: coordinates, and the
    estimates of converged pixels (:func:`_impossible`). :func:`make_dataset` keeps them
    too, so a result emccdcal wrote always loads."""

    def bad(text):
        return InputError(f"{p}: not a valid result: {text}")

    for dim in ("row", "col"):
        c = np.asarray(ds[dim].values)
        if c.dtype.kind not in "iu" or (c.size > 1 and np.any(np.diff(c) != 1)):
            raise bad(f"its {dim} coordinate is not consecutive pixel indices")
    if "setpoint" in ds.coords:
        sp = np.asarray(ds["setpoint"].values, dtype=float)
        if not np.all(np.isfinite(sp) & (sp > 0)) or np.unique(sp).size != sp.size:
            raise bad("its set-points are not distinct positive numbers")
    if ds["converged"].shape != (ds.sizes["row"], ds.sizes["col"]):
        raise bad("converged is not a (row, col) map")
    _, first = _impossible(ds)
    if first is not None:
        raise bad(first)


def load(path) -> xr.Dataset:
    """Read a result that :func:`emccdcal.calibrate` (``out=``) or ``emccdcal calibrate`` wrote,
    checking that it is one.

    Parameters
    ----------
    path : str or Path
        A ``calibration.nc`` file, or a directory that holds one.

    Returns
    -------
    xarray.Dataset
        Loaded into memory (the file is closed on return).

    Raises
    ------
    FileNotFoundError
        No such file (or no ``calibration.nc`` in the directory).
    ValueError
        The file is not a NetCDF/HDF5 file, is not an emccdcal result (no ``method`` or
        ``emccdcal_version`` attribute, or a standard variable missing), or was written by
        an incompatible major version of emccdcal. The message names the file.

    Examples
    --------
    >>> import tempfile, emccdcal
    >>> work = tempfile.mkdtemp()
    >>> sim = emccdcal.simulate_gain_series(
    ...     f"{work}/gs", rows=4, cols=4, frames=400, setpoints=(1, 10), seed=1, progress=False
    ... )
    >>> _ = emccdcal.calibrate(sim.manifest, e_per_adu=3.859, out=f"{work}/out", progress=False)
    >>> ds = emccdcal.load_result(f"{work}/out")
    >>> ds.attrs["method"], ds.em_gain.dims
    ('gs', ('setpoint', 'row', 'col'))
    """
    p = Path(path)
    if p.is_dir():
        p = p / CALIBRATION_FILE
    if not p.is_file():
        raise MissingFileError(f"{p}: no such file")
    return _checked(read_netcdf(p), p)


def _checked_in_memory(ds) -> xr.Dataset:
    """A result in memory (what :func:`emccdcal.calibrate` returns), checked as a file
    is (:func:`load`)."""
    if not isinstance(ds, xr.Dataset):
        raise OptionError(f"a calibration result is an xarray.Dataset, not {type(ds).__name__}")
    return _checked(ds.copy(), "the result given")


def _checked(ds, p) -> xr.Dataset:
    """``ds`` if it is an emccdcal result this version reads (``p`` names it)."""
    missing_attrs = [a for a in ("method", "emccdcal_version") if a not in ds.attrs]
    if missing_attrs:
        raise InputError(
            f"{p}: not an emccdcal calibration result (no {' or '.join(missing_attrs)} attribute)"
        )
    missing = [v for v in REQUIRED_VARIABLES if v not in ds.variables]
    if missing:
        raise InputError(
            f"{p}: not a complete emccdcal result (missing variables: {', '.join(missing)})"
        )
    file_major, our_major = _major(ds.attrs["emccdcal_version"]), _major(_package_version())
    if file_major is None or (our_major is not None and file_major != our_major):
        raise InputError(
            f"{p}: written by emccdcal {ds.attrs['emccdcal_version']}, which is not compatible "
            f"with this emccdcal {_package_version()} (different major version)"
        )
    if ds["converged"].dtype != bool:
        ds["converged"] = ds["converged"].astype(bool)
    _check_domain(ds, p)
    return ds


# --------------------------------------------------------------------------------------
# A calibration to use: one result, or a group of them merged
# --------------------------------------------------------------------------------------
#: Methods that measure φ; in a group, φ comes from the one member that did.
_PHI_METHODS = ("is-adu", "mv-adu")


def _robust_sd(values) -> float | None:
    """1.4826 × the median absolute deviation: the SD of normal values, robust to a
    few outlying pixels."""
    values = values[np.isfinite(values)]
    if values.size < 2:
        return None
    return float(1.4826 * np.median(np.abs(values - np.median(values))))


def pixel_statistics(values) -> dict:
    """``{"median", "spread", "se_of_median", "n"}`` of a map's finite values: the median over
    pixels, its robust spread (1.4826 × MAD, in the map's units), the standard error of
    that median (√(π/2) × spread / √n, as for normal values; it includes the pixels' real
    spread, so it is conservative for the sensor's value) and how many pixels there were.
    Spread and SE are None for fewer than two values.

    Examples
    --------
    >>> pixel_statistics(np.array([[1.0, 2.0], [3.0, np.nan]]))
    {'median': 2.0, 'spread': 1.4826, 'se_of_median': 1.0728..., 'n': 3}
    """
    values = np.asarray(values, dtype=float).ravel()
    finite = values[np.isfinite(values)]
    spread = _robust_sd(finite)
    return {
        "median": float(np.median(finite)) if finite.size else None,
        "spread": spread,
        "se_of_median": None
        if spread is None
        else math.sqrt(math.pi / 2) * spread / math.sqrt(finite.size),
        "n": int(finite.size),
    }


@dataclass(frozen=True)
class Calibration:
    """A calibration ready to use: per-pixel φ, and per set-point the gain, offset and read
    noise, each with what its result says of it.

    Read with :func:`load_calibration` from one result or a group (an ``is-adu`` result
    with ``is-gain`` results, say). Maps are NaN where the pixel did not converge.

    Attributes
    ----------
    label : str
        How it was named: a file, or files joined by commas.
    files : tuple of Path
        The result files it was read from.
    sha256 : tuple of str
        SHA-256 (hex) of each file's bytes, in the order of ``files``: provenance.
    method : str
        The method of the result, or the members' methods joined by ``+``.
    e_per_adu, e_per_adu_se : ndarray, shape (R, C)
        φ (e⁻/ADU) and its standard error (NaN where the result has none: a φ held fixed).
    em_gain, em_gain_se : dict of float to ndarray (R, C)
        Gain per set-point (dimensionless) and its SE; set-point 1 excluded (it is 1).
    offset, read_noise : dict of float to ndarray (R, C)
        Offset S0 and read-noise σ (ADU) per set-point where the results record them:
        from the first member that has the set-point (the median over an intensity
        series' levels).
    em_model : noise.EMModel
        The EM register model the gains were fitted with (the gamma model for results
        that record none).
    camera : dict
        What the stacks recorded of the camera (``serial``, ``model``, ``amplifier``,
        ``readout_rate_mhz``, ``analog_gain``, ``adc_bits``), merged over members.
    origin : tuple of int or None
        ``(row, col)`` of the first pixel on the sensor, where known.
    binning : tuple of int or None
        ``(x, y)`` binning the frames were read out with, where recorded.
    created : str
        Creation time of the newest member (ISO 8601 UTC).
    predicted : dict of float to dict
        Set-points not measured whose gain a gain curve predicts
        (:func:`emccdcal.export.gain_curve.calibration_at`): ``gain`` and ``se_of_median``
        of the sensor, ``extrapolated``, the ``curve`` it came from and the
        ``dark_setpoint`` whose offset and read noise stand in. Empty for a calibration
        read from results; recorded in :meth:`provenance`.

    Examples
    --------
    What every function that takes a calibration reads the Dataset of
    :func:`emccdcal.calibrate`, or a result's path, as:

    >>> import tempfile, emccdcal
    >>> sim = emccdcal.simulate_gain_series(
    ...     tempfile.mkdtemp(), rows=4, cols=4, frames=400, setpoints=(1, 10), seed=1,
    ...     progress=False,
    ... )
    >>> ds = emccdcal.calibrate(sim.manifest, e_per_adu=sim.truth["e_per_adu"], progress=False)
    >>> cal = emccdcal.load_calibration(ds)
    >>> cal.method, cal.setpoints, cal.gain(10).shape
    ('gs', (1.0, 10.0), (4, 4))
    """

    label: str
    files: tuple
    method: str
    e_per_adu: np.ndarray
    em_gain: dict
    e_per_adu_se: np.ndarray | None = None
    em_gain_se: dict = field(default_factory=dict)
    offset: dict = field(default_factory=dict)
    read_noise: dict = field(default_factory=dict)
    em_model: object = None
    camera: dict = field(default_factory=dict)
    origin: tuple | None = None
    binning: tuple | None = None
    created: str = ""
    sha256: tuple = ()
    predicted: dict = field(default_factory=dict)

    @property
    def setpoints(self) -> tuple:
        """Set-points it has a gain for, 1 included (sorted)."""
        return tuple(sorted({1.0, *map(float, self.em_gain)}))

    @property
    def shape(self) -> tuple:
        """(rows, cols) of its maps."""
        return self.e_per_adu.shape

    def _missing(self, what, setpoint):
        have = ", ".join(format_setpoint(v) + "x" for v in self.setpoints)
        return OptionError(
            f"{self.label}: {what}set-point {format_setpoint(setpoint)}x is missing from this "
            f"calibration (it has {have}); add a result that has it, e.g. "
            "adu.nc,gain5x.nc,... (or predict it: emccdcal gain-curve)"
        )

    def gain(self, setpoint) -> np.ndarray:
        """Gain map at a set-point (1 at set-point 1).

        Raises
        ------
        OptionError
            The set-point is not in the calibration (the message names its files).
        """
        s = float(setpoint)
        if s == 1.0:
            return np.ones_like(self.e_per_adu)
        if s not in self.em_gain:
            raise self._missing("", s)
        return self.em_gain[s]

    def gain_se(self, setpoint) -> np.ndarray:
        """SE of the gain map at a set-point (0 at set-point 1)."""
        s = float(setpoint)
        if s == 1.0:
            return np.zeros_like(self.e_per_adu)
        self.gain(s)
        return self.em_gain_se.get(s, np.full_like(self.e_per_adu, np.nan))

    def dark(self, setpoint) -> tuple[np.ndarray, np.ndarray]:
        """Offset and read-noise maps (ADU) at a set-point.

        Raises
        ------
        OptionError
            No member recorded the offset at that set-point.
        """
        s = float(setpoint)
        if s not in self.offset:
            have = ", ".join(format_setpoint(v) + "x" for v in sorted(self.offset)) or "none"
            raise OptionError(
                f"{self.label}: no offset recorded at set-point {format_setpoint(s)}x "
                f"(offsets at: {have}); give the offset of the camera at that set-point"
            )
        return self.offset[s], self.read_noise.get(s, np.full_like(self.offset[s], np.nan))

    def identity(self) -> dict:
        """What identifies the camera and its read-out state: ``camera`` with ``binning``."""
        return {**self.camera, **({} if self.binning is None else {"binning": self.binning})}

    def provenance(self) -> dict:
        """What a file made from this calibration records of where it came from."""
        from . import __version__

        doc = {
            "emccdcal_version": __version__,
            "method": self.method,
            "created": self.created,
            "em_model": str(self.em_model),
            "results": [{"file": str(f), "sha256": h} for f, h in zip(self.files, self.sha256)],
        }
        if self.predicted:
            doc["predicted_gains"] = [
                {"setpoint": s, **p} for s, p in sorted(self.predicted.items())
            ]
        return doc


#: What must agree between a calibration and the frames it is used on (where both
#: record it), with how to name it.
IDENTITY_FIELDS = defaults.IDENTITY_FIELDS


def identity_attrs(manifest) -> dict:
    """The attributes by which every result knows the camera, read-out state and pixels it
    holds for: ``camera`` (JSON), ``binning`` and ``sensor_origin``, as far as the
    manifest's frames record them."""
    attrs: dict[str, object] = {"camera": json.dumps(manifest.camera)} if manifest.camera else {}
    if manifest.origin is not None:
        attrs["sensor_origin"] = np.array(manifest.origin, dtype=np.int64)
    if manifest.binning is not None:
        attrs["binning"] = np.array(manifest.binning, dtype=np.int64)
    return attrs


def result_files(specs) -> list[Path]:
    """The result files named by ``specs`` (files, directories, comma-joined groups, and
    results in memory that were read or written)."""
    files = []
    for spec in specs:
        for part in _members(spec):
            if isinstance(part, xr.Dataset):  # in memory: the file it was read or written as
                part = part.encoding.get("source")
            if part is not None:
                p = Path(part)
                files.append(p / CALIBRATION_FILE if p.is_dir() else p)
    return files


def camera_of(ds, path) -> dict:
    """What a result records of its camera (``attrs["camera"]``, JSON), checked."""
    text = ds.attrs.get("camera", "{}")
    try:
        camera = json.loads(str(text))
        if not isinstance(camera, dict):
            raise ValueError("not an object")
    except ValueError as exc:
        raise InputError(f"{path}: its camera attribute is not a JSON object ({exc})") from None
    return camera


def _members(spec):
    """The members of a calibration argument: paths (text) and results in memory."""
    if isinstance(spec, xr.Dataset):
        return [spec]
    if isinstance(spec, (str, Path)) and "," in str(spec) and Path(spec).exists():
        return [str(spec)]  # a path with a comma in its name
    if isinstance(spec, (list, tuple)):
        parts = [p if isinstance(p, xr.Dataset) else str(p) for p in spec]
    else:
        parts = [p.strip() for p in str(spec).split(",")]
    parts = [p for p in parts if isinstance(p, xr.Dataset) or p]
    if not parts:
        raise OptionError(f"empty calibration argument {spec!r}")
    return parts


def _span(values):
    values = np.asarray(values)
    return f"{values.min()}–{values.max()}" if values.size else "(none)"


def _acquisition_setpoints(ds, dim):
    """The set-point of each entry of a per-acquisition dimension: the set-points
    themselves, or for ``level`` the result's one set-point (an intensity series)."""
    if dim == "setpoint":
        return ds["setpoint"].values.astype(float)
    setpoints = ds["setpoint"].values.astype(float) if "setpoint" in ds.coords else [1.0]
    return np.full(ds.sizes[dim], float(setpoints[0]) if len(setpoints) == 1 else np.nan)


def _load_members(parts, label, shape, of) -> list:
    """``[(file, dataset)]`` of a group's members, each given once and, where ``shape``
    is given, covering exactly that sensor region."""
    loaded: list = []
    for part in parts:
        if isinstance(part, xr.Dataset):  # a result in memory: checked as a file is
            ds = _checked_in_memory(part)
            # its file, where it was read from one or written to one (its provenance)
            loaded.append((Path(ds.encoding.get("source", "<the result given>")), ds))
            continue
        p = Path(part)
        ds = load(p)
        f = p / CALIBRATION_FILE if p.is_dir() else p
        twice = [g for g, _ in loaded if g.resolve() == f.resolve()]
        if twice:
            raise OptionError(f"{label}: {f} is given twice; give each result once")
        rows, cols = ds["row"].values, ds["col"].values
        if shape is not None:
            R, C = shape
            if not (np.array_equal(rows, np.arange(R)) and np.array_equal(cols, np.arange(C))):
                raise OptionError(
                    f"{f}: calibration covers rows {_span(rows)} and columns {_span(cols)}, "
                    f"but {of} are {R}×{C} (rows 0–{R - 1}, columns 0–{C - 1}); "
                    "a calibration of the same sensor region is needed"
                )
        loaded.append((f, ds))
    return loaded


def _members_em_model(label, loaded):
    """The one register model of a group's members: that of those that measured a gain
    (1x has no register); of a 1x-only group, the model it was fitted with, else the
    default."""
    from .model.noise import EMModel

    models = {
        EMModel.from_attrs(ds.attrs)
        for _, ds in loaded
        if "em_gain" in ds and np.any(ds["setpoint"].values != 1)
    } - {None}
    if len(models) > 1:
        raise OptionError(
            f"{label}: its members were fitted with different EM register "
            f"models ({', '.join(sorted(map(str, models)))}); group results "
            "of one model"
        )
    if not models:  # 1x only (is-adu): the model it was fitted with, else the default's
        models = {
            next(
                (m for m in (EMModel.from_attrs(ds.attrs) for _, ds in loaded) if m),
                EMModel(defaults.DEFAULT_EM_MODEL),
            )
        }
    return models.pop()


def load_calibration(spec, shape=None, *, of="the frames") -> Calibration:
    """A calibration from what a user has: a result file, a result in memory, or a group
    of them merged; the one door every function that takes a calibration goes through.

    Parameters
    ----------
    spec : str, Path, xarray.Dataset, Calibration or sequence of them
        A ``calibration.nc`` file or its directory, or several joined by commas; a
        result as :func:`emccdcal.calibrate` or :func:`load` returns it; a
        :class:`Calibration` (returned as it is, checked against ``shape``).
    shape : (int, int), optional
        The frames' (rows, cols): every file must cover exactly that sensor region
        (``row`` = 0 … rows − 1 and ``col`` = 0 … cols − 1).
    of : str
        What ``shape`` belongs to, for the message when a file does not fit it.

    Returns
    -------
    Calibration

    Raises
    ------
    FileNotFoundError, ValueError
        A missing or unreadable file, one of another sensor size or region, two members
        giving the same set-point, two members that both measured φ, or members fitted
        with different register models. The message names the file.

    Examples
    --------
    >>> import tempfile, emccdcal
    >>> work = tempfile.mkdtemp()
    >>> sim = emccdcal.simulate_gain_series(
    ...     f"{work}/gs", rows=4, cols=4, frames=400, setpoints=(1, 10), seed=1, progress=False
    ... )
    >>> ds = emccdcal.calibrate(sim.manifest, e_per_adu=sim.truth["e_per_adu"], progress=False)
    >>> cal = emccdcal.load_calibration(ds)
    >>> cal.setpoints, cal.gain(10).shape
    ((1.0, 10.0), (4, 4))
    """

    if isinstance(spec, Calibration):
        if shape is not None and tuple(spec.e_per_adu.shape) != tuple(shape):
            raise OptionError(
                f"{spec.label}: calibration of {spec.e_per_adu.shape[0]}×"
                f"{spec.e_per_adu.shape[1]} px, but {of} are {shape[0]}×{shape[1]}"
            )
        return spec
    parts = _members(spec)
    label = ",".join(p if isinstance(p, str) else "the result given" for p in parts)
    loaded = _load_members(parts, label, shape, of)
    shapes = {(ds.sizes["row"], ds.sizes["col"]) for _, ds in loaded}
    if len(shapes) > 1:
        raise OptionError(f"{label}: the files cover different sensor regions {sorted(shapes)}")
    methods = [str(ds.attrs.get("method", "?")) for _, ds in loaded]

    def masked(ds, name):
        if name not in ds:
            return None
        ok = ds["converged"].transpose("row", "col").values.astype(bool)
        return np.where(ok, ds[name].transpose(..., "row", "col").values.astype(float), np.nan)

    phi_from = [i for i, m in enumerate(methods) if m in _PHI_METHODS]
    if len(phi_from) > 1:
        raise OptionError(
            f"{label}: {loaded[phi_from[0]][0]} and {loaded[phi_from[1]][0]} both measured "
            "e_per_adu; a group takes phi from one of them"
        )
    i_phi = phi_from[0] if phi_from else 0
    phi = masked(loaded[i_phi][1], "e_per_adu")
    gains: dict = {}
    gains_se: dict = {}
    source: dict = {}
    offsets: dict = {}
    read_noise: dict = {}
    camera: dict = {}
    other_phi = []
    for f, ds in loaded:
        for name, store in (("offset", offsets), ("read_noise", read_noise)):
            maps = masked(ds, name)
            if maps is None:
                continue
            dim = ds[name].dims[0] if ds[name].ndim == 3 else None
            at = _acquisition_setpoints(ds, dim) if dim else [1.0]
            maps = maps if dim else maps[None]
            for s in dict.fromkeys(at):  # first member first; levels at one set-point merged
                if np.isfinite(s) and s not in store:
                    store[s] = np.nanmedian(maps[np.asarray(at) == s], axis=0)
        recorded = camera_of(ds, f)
        differ = identity.mismatches(camera, recorded)
        if differ:
            raise OptionError(
                f"{label}: {f} is of another camera or read-out state than "
                f"the members before it: {'; '.join(differ.values())}"
            )
        camera.update({k: v for k, v in recorded.items() if k not in camera})
        if "em_gain" not in ds:
            continue
        g, g_se = masked(ds, "em_gain"), masked(ds, "em_gain_se")
        for j, s in enumerate(ds["setpoint"].values.astype(float)):
            if s == 1.0:
                continue
            if s in gains:
                raise OptionError(
                    f"{label}: set-point {format_setpoint(s)}x is in both {source[s]} "
                    f"and {f}; give each set-point once"
                )
            gains[s], gains_se[s], source[s] = g[j], g_se[j], f
        # g/φ is what a gain fit measures: note members fitted with another φ.
        other = masked(ds, "e_per_adu")
        both = np.isfinite(other) & np.isfinite(phi)
        if len(loaded) > 1 and both.any() and not np.allclose(other[both], phi[both], rtol=1e-6):
            other_phi.append(f"{f.name} ({np.median(other[both]):.4g})")
    if other_phi:
        warnings.warn(
            f"{label}: gains of {', '.join(other_phi)} were fitted with another e_per_adu "
            f"(median, e-/ADU) than the group's phi from {loaded[i_phi][0].name} "
            f"({np.nanmedian(phi):.4g}); the group uses its phi",
            stacklevel=2,
            category=InputWarning,
        )
    model = _members_em_model(label, loaded)
    origins = {
        tuple(int(v) for v in ds.attrs["sensor_origin"])
        for _, ds in loaded
        if "sensor_origin" in ds.attrs
    }
    binnings = {
        tuple(int(v) for v in np.atleast_1d(ds.attrs["binning"]))
        for _, ds in loaded
        if "binning" in ds.attrs
    }
    if len(binnings) > 1:
        raise OptionError(
            f"{label}: its members were read out with different binnings "
            f"({', '.join('x'.join(map(str, b)) for b in sorted(binnings))})"
        )
    return Calibration(
        label=label,
        files=tuple(f for f, _ in loaded),
        method="+".join(dict.fromkeys(methods)),
        e_per_adu=phi,
        e_per_adu_se=masked(loaded[i_phi][1], "e_per_adu_se"),
        em_gain=gains,
        em_gain_se=gains_se,
        offset=offsets,
        read_noise=read_noise,
        em_model=model,
        camera=camera,
        origin=origins.pop() if len(origins) == 1 else None,
        binning=binnings.pop() if binnings else None,
        created=max(str(ds.attrs.get("created", "")) for _, ds in loaded),
        sha256=tuple(ds.encoding.get("sha256", "") for _, ds in loaded),
    )
