"""What every figure shares: units' words, the panels' grid, converged values, the set-points and φ a result holds, the default pixel, and writing a figure (PNG bytes, an atomic file)."""

from __future__ import annotations

import math
from io import BytesIO
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from ..._output import atomic_write
from ...errors import InputError


E_UNIT = "e$^-$"
DIMLESS = "(dimensionless)"
_SE_NOTE = "median over converged pixels ± median per-pixel SE"
_MIN_WIDTH = 7.0  # inches: a figure's title fits


class DataUnavailable(InputError):
    """The data a figure needs cannot be found or no longer match the result."""


# --------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------
def _grid(nrows, ncols, size, *, gap=(0.85, 0.95), margins=(0.8, 0.3, 0.65, 0.55)):
    """A figure of ``nrows × ncols`` axes, each ``size`` = (width, height) inches.

    Fixed margins in inches (``gap`` between axes; ``margins`` = left, right, top, bottom)
    instead of a layout engine: constrained layout costs seconds on the many-panel maps.
    """
    (w, h), (gw, gh), (left, right, top, bottom) = size, gap, margins
    W = left + right + ncols * w + (ncols - 1) * gw
    if W < _MIN_WIDTH:  # room for the title: centre a narrow grid
        left, right = left + (_MIN_WIDTH - W) / 2, right + (_MIN_WIDTH - W) / 2
        W = _MIN_WIDTH
    H = top + bottom + nrows * h + (nrows - 1) * gh
    fig = Figure(figsize=(W, H))
    axes = fig.subplots(
        nrows,
        ncols,
        squeeze=False,
        gridspec_kw=dict(
            left=left / W,
            right=1 - right / W,
            bottom=bottom / H,
            top=1 - top / H,
            wspace=gw / w,
            hspace=gh / h,
        ),
    )
    return fig, axes


def _panels(n, ncols, size=(3.3, 2.2), **kw):
    """A figure with ``n`` visible axes in a grid of ``ncols`` columns (see :func:`_grid`)."""
    ncols = max(1, min(ncols, n))
    fig, axes = _grid(math.ceil(n / ncols), ncols, size, **kw)
    axes = axes.ravel()
    for ax in axes[n:]:
        ax.set_visible(False)
    return fig, list(axes[:n])


def _labels(results, labels):
    """Legend labels: the method, with a number where two results share one."""
    if labels is not None:
        return list(labels)
    methods = [str(ds.attrs.get("method", "?")) for ds in results]
    return [m if methods.count(m) == 1 else f"{m} #{i + 1}" for i, m in enumerate(methods)]


def _converged_values(da, conv):
    """Finite values of a (row, col) DataArray at the converged pixels, as a 1-D array."""
    v = np.asarray(da.transpose("row", "col").values, dtype=float)[conv]
    return v[np.isfinite(v)]


def _conv(ds):
    return ds["converged"].transpose("row", "col").values.astype(bool)


_FITS_PHI = {"is-adu", "mv-adu"}
_HOLDS_PHI = {"is-gain", "mv-gain", "gs", "gs-no1x", "gs-hierarchical"}


def _estimated_phi(ds):
    """Whether the result fitted φ (rather than holding a given value)."""
    method = ds.attrs.get("method")
    if method in _FITS_PHI | _HOLDS_PHI:
        return method in _FITS_PHI
    se = np.asarray(ds["e_per_adu_se"].values, dtype=float)  # another method: a fitted φ has SEs
    return bool(np.any(np.isfinite(se) & (se > 0)))


def _gain_setpoints(ds):
    if "em_gain" not in ds:
        return []
    return [float(s) for s in ds["setpoint"].values if float(s) != 1.0]


def default_pixel(ds):
    """The pixel shown by the single-pixel figures: the central one, if it converged.

    Parameters
    ----------
    ds : xarray.Dataset
        A calibration result.

    Returns
    -------
    (int, int)
        Sensor (row, col) index (pixel): the centre of the grid, or the first converged
        pixel in C order when the centre did not converge.
    """
    rows, cols = ds["row"].values, ds["col"].values
    r, c = int(rows[len(rows) // 2]), int(cols[len(cols) // 2])
    conv = _conv(ds)
    if not conv[len(rows) // 2, len(cols) // 2] and conv.any():
        i, j = np.argwhere(conv)[0]
        r, c = int(rows[i]), int(cols[j])
    return r, c


# --------------------------------------------------------------------------------------
# Output
# --------------------------------------------------------------------------------------
def figure_png(fig, dpi=96):
    """The figure as PNG bytes."""
    buf = BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


def save_figure(fig, stem, *, dpi=150):
    """Write a figure as ``<stem>.png`` and ``<stem>.svg``, each atomically.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
    stem : str or Path
        Path without suffix; its directory is created if missing.
    dpi : int, optional
        Resolution of the PNG (dots per inch).

    Returns
    -------
    (Path, Path)
        The PNG and SVG files.
    """
    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    out = []
    for fmt in ("png", "svg"):
        path = stem.with_name(f"{stem.name}.{fmt}")
        atomic_write(path, lambda p, fmt=fmt: fig.savefig(p, format=fmt, dpi=dpi))
        out.append(path)
    return tuple(out)
