"""A result on disk: a run recorded (:func:`run_recorded`), saved (:func:`save`: ``calibration.nc`` and ``summary.json``) and loaded back (:func:`load`), checked to be a result and possible."""

from __future__ import annotations

import json
import time
import warnings
from pathlib import Path

import numpy as np
import xarray as xr

from .._output import file_sha256, read_netcdf, write_netcdf
from ..errors import InputError, MissingFileError, OptionError
from ..errors import issue_once_per_kind
from .schema import CALIBRATION_FILE, REQUIRED_VARIABLES, SUMMARY_FILE, _major, _package_version
from .summary import summarize


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
    from ..runstore import publish

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
