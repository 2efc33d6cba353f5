"""The estimates of one or more results (:func:`estimates_figure`) and their maps over the sensor (:func:`maps_figure`)."""

from __future__ import annotations


import numpy as np
from matplotlib.ticker import MaxNLocator

from ...result import format_setpoint
from .common import (
    DIMLESS,
    DataUnavailable,
    E_UNIT,
    _conv,
    _converged_values,
    _estimated_phi,
    _gain_setpoints,
    _grid,
    _labels,
    _panels,
)


# --------------------------------------------------------------------------------------
# (3) Distributions of per-pixel estimates
# --------------------------------------------------------------------------------------
def estimates_figure(results, *, labels=None):
    """Distributions of the per-pixel φ and gains, per method and set-point.

    One panel for φ (results that fitted it) and one per gain set-point other than 1
    (results with ``em_gain``), each with one step histogram per result over shared
    bins (converged pixels, finite values). The set-point is marked by a dotted line
    when it lies near the estimates; it is named in the panel title in any case.

    Parameters
    ----------
    results : sequence of xarray.Dataset
        Calibration results to compare.
    labels : sequence of str, optional
        Legend labels (default: the methods).

    Returns
    -------
    matplotlib.figure.Figure

    Raises
    ------
    DataUnavailable
        No result fitted φ or a gain.
    """
    results = list(results)
    labels = _labels(results, labels)
    panels = []  # (title, xlabel, setpoint or None, [(label, values)])
    phis = [
        (lab, _converged_values(ds["e_per_adu"], _conv(ds)))
        for lab, ds in zip(labels, results)
        if _estimated_phi(ds)
    ]
    if phis:
        panels.append(("ADU conversion factor φ", f"φ ({E_UNIT}/ADU)", None, phis))
    for s in sorted({s for ds in results for s in _gain_setpoints(ds)}):
        vals = [
            (lab, _converged_values(ds["em_gain"].sel(setpoint=s), _conv(ds)))
            for lab, ds in zip(labels, results)
            if s in _gain_setpoints(ds)
        ]
        panels.append(
            (f"EM gain at set-point {format_setpoint(s)}×", f"true EM gain g {DIMLESS}", s, vals)
        )
    if not panels:
        raise DataUnavailable("no result fitted φ or an EM gain: no distributions to show")
    fig, axes = _panels(len(panels), 3)
    for ax, (title, xlabel, s, vals) in zip(axes, panels):
        every = np.concatenate([v for _, v in vals])
        if every.size == 0:
            ax.text(0.5, 0.5, "no converged pixel", ha="center", transform=ax.transAxes)
        else:
            nb = int(np.clip(np.sqrt(every.size) * 1.5, 5, 40))
            lo, hi = every.min(), every.max()
            edges = np.linspace(lo, hi, nb + 1) if hi > lo else np.array([lo - 0.5, hi + 0.5])
            for j, (lab, v) in enumerate(vals):  # line styles keep coinciding results visible
                ax.hist(
                    v,
                    bins=edges,
                    histtype="step",
                    lw=1.6,
                    color=f"C{j % 10}",
                    ls=("-", "--", "-.", ":")[j % 4],
                    label=f"{lab} (n = {v.size})",
                )
            if s is not None and lo - 0.5 * (hi - lo + 0.1 * hi) <= s <= hi + 0.5 * (
                hi - lo + 0.1 * hi
            ):
                ax.axvline(s, color="k", ls=":", lw=1.2, label=f"set-point {format_setpoint(s)}×")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("pixels (count)")
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
        ax.legend(fontsize=7)
    fig.suptitle("Per-pixel estimates (converged pixels)", fontsize=11)
    return fig


# --------------------------------------------------------------------------------------
# (4) Maps
# --------------------------------------------------------------------------------------
def _acq_maps(ds, var):
    """(title suffix, 2-D array) per acquisition of a (setpoint|level, row, col) variable."""
    da = ds[var]
    dim = next(d for d in da.dims if d not in ("row", "col"))
    fmt = (lambda v: f"{format_setpoint(v)}×") if dim == "setpoint" else str
    return [(fmt(v), da.sel({dim: v}).transpose("row", "col").values) for v in da[dim].values]


def maps_figure(ds):
    """Maps over the sensor of φ, the gains, offset, read noise, convergence and gof p-value.

    Parameters
    ----------
    ds : xarray.Dataset
        A calibration result. Variables it lacks (``offset``, ``read_noise`` and
        ``gof_pvalue`` are absent for mean–variance results) are left out.

    Returns
    -------
    matplotlib.figure.Figure
        One row per quantity, one panel per set-point or level, each with a colour bar
        in the quantity's unit; axes are sensor column and row (px).
    """
    conv = _conv(ds)
    phi_title = "φ" + ("" if _estimated_phi(ds) else " (given, not fitted)")
    rows = [
        [
            (
                phi_title,
                ds["e_per_adu"].transpose("row", "col").values,
                f"φ ({E_UNIT}/ADU)",
                "viridis",
                None,
            ),
            (
                f"converged: {int(conv.sum())}/{conv.size}",
                conv.astype(float),
                "converged (1 = yes)",
                "RdYlGn",
                (0, 1),
            ),
        ]
    ]
    if _gain_setpoints(ds):
        rows.append(
            [
                (
                    f"g at {format_setpoint(s)}×",
                    ds["em_gain"].sel(setpoint=s).transpose("row", "col").values,
                    f"g {DIMLESS}",
                    "viridis",
                    None,
                )
                for s in _gain_setpoints(ds)
            ]
        )
    for var, name, unit, cmap in (
        ("offset", "offset S0", "S0 (ADU)", "cividis"),
        ("read_noise", "read noise σ", "σ (ADU)", "cividis"),
    ):
        if var in ds:
            maps = _acq_maps(ds, var)
            if all(np.array_equal(a, maps[0][1], equal_nan=True) for _, a in maps):
                maps = [("every acquisition", maps[0][1])]  # one dark for all (1× series)
            rows.append([(f"{name}, {t}", a, unit, cmap, None) for t, a in maps])
    if "gof_pvalue" in ds:
        rows.append(
            [
                (f"gof p-value, {t}", a, f"p {DIMLESS}", "magma", (0, 1))
                for t, a in _acq_maps(ds, "gof_pvalue")
            ]
        )
    ncols = max(len(r) for r in rows)
    packed = []  # short rows share a line
    for r in rows:
        if packed and len(packed[-1]) + len(r) <= ncols:
            packed[-1] = packed[-1] + r
        else:
            packed.append(r)
    rows = packed
    fig, axes = _grid(
        len(rows), ncols, (2.2, 2.0), gap=(1.35, 0.75), margins=(0.8, 1.0, 0.65, 0.55)
    )
    r0, r1 = int(ds.row[0]), int(ds.row[-1])
    c0, c1 = int(ds.col[0]), int(ds.col[-1])
    for i, row in enumerate(rows):
        for j in range(ncols):
            ax = axes[i, j]
            if j >= len(row):
                ax.set_visible(False)
                continue
            title, arr, unit, cmap, lim = row[j]
            vmin, vmax = lim if lim else (None, None)
            im = ax.imshow(
                np.asarray(arr, dtype=float),
                cmap=cmap,
                vmin=vmin,
                vmax=vmax,
                extent=(c0 - 0.5, c1 + 0.5, r1 + 0.5, r0 - 0.5),
                interpolation="nearest",
            )
            fig.colorbar(im, ax=ax, label=unit, shrink=0.9)
            ax.set_title(title, fontsize=9)
            ax.set_xlabel("column (px)", fontsize=8)
            ax.set_ylabel("row (px)", fontsize=8)
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
            ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    fig.suptitle(f"{ds.attrs.get('method')}: maps over the sensor", fontsize=11)
    return fig
