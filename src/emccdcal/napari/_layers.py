"""A calibration's maps as napari layers, labelled with their units (no Qt needed)."""

from __future__ import annotations

import numpy as np

from ..data.telegraph import MAX_STATES
from ..result.flags import PIXEL_FLAGS

__all__ = ["result_layers"]


def result_layers(ds, *, prefix: str = "") -> list[tuple]:
    """The maps of a calibration result as layer data ``(array, kwargs, "image")``.

    φ (e-/ADU), the true gain at each multiplied set-point, the intensity (e-), the
    offset and read noise (ADU) and goodness-of-fit p-value of the acquisitions (one
    layer each, the acquisitions along its first axis, named in its metadata), and the
    pixels the dark frames flagged (:data:`emccdcal.result.flags.PIXEL_FLAGS`: 1 where
    found, at every pixel) with the random-telegraph pixels' offset states (1 to 4);
    each named with its unit, the maps NaN where a pixel did not converge, contrast from
    the 1st to the 99th percentile, placed at the calibration's sensor origin, hidden but
    the last.

    Parameters
    ----------
    ds : xarray.Dataset
        A result (:func:`emccdcal.load_result`).
    prefix : str
        Put before every name (e.g. the method).
    """
    origin = tuple(float(v) for v in ds.attrs.get("sensor_origin", (0, 0)))
    ok = ds.converged.values.astype(bool)
    layers = []

    def add(values, name, unit, colormap="viridis", axis=None, everywhere=False, limits=None):
        data = np.asarray(values, dtype=float)
        data = data if everywhere else np.where(ok, data, np.nan)
        finite = data[np.isfinite(data)]
        if limits is None:
            limits = (np.percentile(finite, [1, 99]) if finite.size else [0.0, 1.0]).tolist()
        if limits[0] == limits[1]:
            limits = [limits[0] - 0.5, limits[1] + 0.5]
        metadata = {"units": unit, "variable": name}
        if axis is not None:
            metadata[axis[0]] = axis[1]
        # a dimensionless map has no unit in its name: "(1)" reads as napari's numbering
        label = f"{prefix}{name}" + ("" if unit == "1" else f" ({unit})")
        layers.append(
            (
                data,
                {
                    "name": label,
                    "colormap": colormap,
                    "contrast_limits": limits,
                    "visible": False,
                    "translate": ((0.0,) if data.ndim == 3 else ()) + origin,
                    "metadata": metadata,
                },
                "image",
            )
        )

    if "e_per_adu" in ds:
        add(ds.e_per_adu.values, "phi", "e-/ADU")
    if "setpoint" in ds.dims and "em_gain" in ds:
        for s in ds.setpoint.values:
            if float(s) != 1.0:
                add(ds.em_gain.sel(setpoint=s).values, f"gain at {float(s):g}x", "1", "magma")
    if "photoelectrons" in ds and ds.photoelectrons.ndim == 2:
        add(ds.photoelectrons.values, "intensity", "e-", "inferno")
    axis = "setpoint" if "setpoint" in ds.dims else "level" if "level" in ds.dims else None
    for var, unit, colormap in (
        ("offset", "ADU", "gray"),
        ("read_noise", "ADU", "gray"),
        ("gof_pvalue", "1", "cividis"),
    ):
        if var in ds:
            keys = (
                None
                if axis not in ds[var].dims
                else (axis, [float(k) if axis == "setpoint" else str(k) for k in ds[axis].values])
            )
            add(ds[var].values, var, unit, colormap, keys)
    if "dark_current" in ds:  # darks at two or more exposures (hot pixels stand out)
        add(ds.dark_current.values, "dark current", "e-/s", "inferno")
    for name, flag in PIXEL_FLAGS.items():  # pixels the darks flagged: 1, else 0
        if name in ds:
            add(ds[name].values, flag.layer, "1", "red", everywhere=True)
    if "telegraph_states" in ds:  # 1 for one normal, 2–4 at a random-telegraph pixel
        top = float(MAX_STATES)
        add(ds.telegraph_states.values, "telegraph states", "1", "plasma", None, True, [1.0, top])
    if layers:
        layers[1 if len(layers) > 1 else 0][1]["visible"] = True  # φ, or the first gain
    return layers
