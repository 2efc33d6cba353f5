"""What a result says in a few numbers and one line: :func:`summarize` (medians with their spread and SE per set-point), :func:`verdict_line` and :func:`is_doubtful`."""

from __future__ import annotations

import json

import numpy as np
import xarray as xr

from .._util import finite_or_none, format_setpoint

from .schema import _PIXEL_DIMS, em_model_summary


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
