"""Making a result (:func:`make_dataset`): the estimates of a run as a labelled Dataset, every variable with its units, the set-points and levels as coordinates, the run's attributes."""

from __future__ import annotations

import datetime as _dt
import warnings
from numbers import Number

import numpy as np
import xarray as xr

from .._util import one_line

from ..errors import FitWarning
from .schema import (
    LONG_NAMES,
    UNITS,
    _HEX64,
    _PIXEL_DIMS,
    _RESERVED_ATTRS,
    _UNITS_NOTE,
    _package_version,
)
from .files import _impossible


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
