"""φ given to a run, checked: a number, a map, or a result that measured it.

``calibrate`` and the verbs that hold φ fixed take it from the caller or the manifest:
a number (e⁻/ADU), a (rows, cols) map, or an ``is-adu``/``mv-adu`` result (its path, the
Dataset :func:`emccdcal.calibrate` returned, or a :class:`emccdcal.Calibration`), whose φ
and standard error per pixel then go into the fit, cropped to the manifest's pixels and
checked to be of the same camera and read-out state (:func:`e_per_adu_inputs`). Before
any fitting, the fit's door refuses a φ the data contradict
(:func:`emccdcal.fit.series.specify`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import identity, result
from .result.files import _checked_in_memory
from ._util import e_per_adu_map
from .data.manifest import Source
from .errors import OptionError

__all__ = ["e_per_adu_inputs"]


def e_per_adu_inputs(manifest, e_per_adu, accept_mismatch=()):
    """φ (e⁻/ADU) map, its standard-error map (or None) and where they came from (or None).

    ``e_per_adu`` (else the manifest's) is a number, a (rows, cols) map, or an ``is-adu``
    or ``mv-adu`` result: its path (``calibration.nc`` or directory), the Dataset
    :func:`calibrate` returned, or a :class:`emccdcal.Calibration`; of a result, φ and its
    standard error per pixel, NaN where it did not converge.
    """
    shape = manifest.shape
    if e_per_adu is None:
        source = manifest.e_per_adu_source
        if source is None or source.kind != "result":
            return e_per_adu_map(manifest.e_per_adu, shape), None, source
        e_per_adu = source.path
    chained = _phi_result(e_per_adu)
    if chained is None:
        return e_per_adu_map(e_per_adu, shape), None, Source("given")
    label, method, phi, se, ok, identity_of, origin, source = chained
    if not any(m in ("is-adu", "mv-adu") for m in method.split("+")):
        raise OptionError(
            f"e_per_adu from {label}: a {method} result does not estimate e_per_adu; "
            "chain an is-adu or mv-adu result"
        )
    identity.check(
        identity_of,
        {manifest.path: manifest.identity()},
        label=f"e_per_adu from {label}",
        accept=accept_mismatch,
        what="frames of the manifest",
    )
    crop = _crop_to(manifest, label, phi.shape, origin)
    phi, se, ok = phi[crop], se[crop], ok[crop]
    ok &= np.isfinite(phi) & (phi > 0)
    if not ok.any():
        raise OptionError(f"e_per_adu from {label}: no pixel of that result converged")
    return np.where(ok, phi, np.nan), np.where(ok, se, np.nan), source


def _phi_result(e_per_adu):
    """Of a chained φ (a result's path, a result Dataset or a Calibration): a label for
    messages, its method, the φ, SE and converged maps, its camera identity, its origin on
    the sensor and its :class:`Source`; None for a number or a map."""
    import xarray as xr

    if isinstance(e_per_adu, result.Calibration):
        cal = e_per_adu
        se = cal.e_per_adu_se if cal.e_per_adu_se is not None else np.full(cal.shape, np.nan)
        source = Source("result", Path(cal.files[0])) if cal.files else Source("given")
        return (
            f"'{cal.label}'",
            cal.method,
            np.asarray(cal.e_per_adu, float),
            np.asarray(se, float),
            np.isfinite(cal.e_per_adu),
            cal.identity(),
            cal.origin,
            source,
        )
    if isinstance(e_per_adu, (str, Path)):
        from .data.manifest import is_result_path

        path = Path(e_per_adu)
        if not is_result_path(path):
            raise OptionError(
                f"e_per_adu '{path}' is not a calibration result (a .nc file or "
                "a result directory); give a number, a map or a result"
            )
        ds, label, source = result.load(path), f"'{path}'", Source("result", path)
    elif isinstance(e_per_adu, xr.Dataset):
        ds = _checked_in_memory(e_per_adu)
        saved = e_per_adu.encoding.get("source")  # a result read from or written to a file
        label = f"'{saved}'" if saved else "the result given"
        source = Source("result", Path(saved)) if saved else Source("given")
    else:
        return None
    binning = ds.attrs.get("binning")
    camera = result.camera_of(ds, label)
    return (
        label,
        str(ds.attrs.get("method")),
        np.asarray(ds.e_per_adu.values, dtype=float),
        np.asarray(ds.e_per_adu_se.values, dtype=float),
        np.asarray(ds.converged.values, dtype=bool),
        {**camera, **({} if binning is None else {"binning": binning})},
        ds.attrs.get("sensor_origin"),
        source,
    )


def _crop_to(manifest, label, shape, origin):
    """The part of a result of ``shape`` at sensor ``origin`` that the manifest's pixels
    cover (slices), or an error saying which rows or columns are missing."""
    shape, want = tuple(shape), tuple(manifest.shape)
    if origin is None or manifest.origin is None:
        if shape != want:
            raise OptionError(
                f"e_per_adu from {label}: its pixels {shape} are not the manifest's {want}, "
                "and where they lie on the sensor is not known (give 'origin' in the "
                "manifests, or files that record their region)"
            )
        return slice(None), slice(None)
    (r0, c0), (m0, n0) = (int(v) for v in origin), manifest.origin
    top, left = m0 - r0, n0 - c0
    if top < 0 or left < 0 or top + want[0] > shape[0] or left + want[1] > shape[1]:
        rows = sorted(set(range(m0, m0 + want[0])) - set(range(r0, r0 + shape[0])))
        cols = sorted(set(range(n0, n0 + want[1])) - set(range(c0, c0 + shape[1])))
        missing = "; ".join(
            f"{what} {v[0]}–{v[-1]}" for what, v in (("rows", rows), ("cols", cols)) if v
        )
        raise OptionError(
            f"e_per_adu from {label} covers sensor rows {r0}–{r0 + shape[0] - 1}, cols "
            f"{c0}–{c0 + shape[1] - 1}; the manifest needs {manifest.rows_cols}: {missing} "
            "missing"
        )
    return slice(top, top + want[0]), slice(left, left + want[1])
