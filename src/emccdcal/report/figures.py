"""Figures of a calibration, modelled on Ryan et al. (2021): matplotlib, object API only.

Every function takes results (xarray datasets from :func:`emccdcal.result.load` or
:func:`emccdcal.calibrate`) and returns a :class:`matplotlib.figure.Figure`; none touches
pyplot's global state, so they are safe in scripts, servers and threads. Every axis label
ends with its unit in parentheses. :func:`save_figure` writes a figure as PNG and SVG.

========================================  =============================================
function                                  shows (paper figure)
========================================  =============================================
:func:`histogram_figure`                  each acquisition's counts of one pixel with the
                                          fitted pmf (Fig. 1); re-reads the raw data
:func:`photon_transfer_figure`            variance against mean per acquisition with the
                                          mean–variance fit lines (Fig. 2a); raw data
:func:`estimates_figure`                  distributions of per-pixel φ and gains, per
                                          method and set-point (Figs. 2b, 3)
:func:`maps_figure`                       maps of φ, gains, offset, read noise,
                                          convergence and goodness of fit
:func:`gain_figure`                       measured gain against set-point, error bars
:func:`bead_intensity_figure`             bead intensities per set-point per method
                                          (Fig. 4), from a validation directory
:func:`bead_consistency_figure`           per-bead mean intensity relative to 1× and the
                                          consistency metric (Fig. 5)
========================================  =============================================

The two raw-data figures find the data through the result's ``manifest_path`` attribute;
when the manifest is gone or has changed since the calibration they raise
:class:`DataUnavailable` (a ``ValueError`` naming the file).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from .._output import atomic_write, plain_text
from ..beads.validation import INTENSITIES_FILE, read_validation
from ..data import stats
from ..data.manifest import read_manifest
from ..errors import InputError, OptionError
from ..fit import mv
from ..model import noise
from ..result import format_setpoint

__all__ = [
    "DataUnavailable",
    "default_pixel",
    "histogram_figure",
    "photon_transfer_figure",
    "estimates_figure",
    "maps_figure",
    "gain_figure",
    "gain_points",
    "bead_intensity_figure",
    "bead_consistency_figure",
    "save_figure",
    "figure_png",
    "write_validation_figures",
    "gain_history_figure",
    "gain_check_figure",
]

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
# Raw data of one pixel
# --------------------------------------------------------------------------------------
@dataclass
class _PixelAcq:
    name: str
    setpoint: float
    values: np.ndarray  # distinct counts (ADU)
    counts: np.ndarray  # frames at each value
    n: int
    mean: float  # ADU
    var: float  # ADU², ddof=1
    offset: float  # ADU
    read_noise: float  # ADU
    params: dict  # photoelectrons (e-), em_gain (1), e_per_adu (e-/ADU)
    gof_pvalue: float


def _pick(ds, var, label, setpoint, r, c):
    """Value of ``var`` for one acquisition (level label, set-point) at pixel (r, c), or None."""
    if var not in ds:
        return None
    da = ds[var]
    if "level" in da.dims:
        if label not in ds["level"].values:
            return None
        da = da.sel(level=label)
    if "setpoint" in da.dims:
        if setpoint not in ds["setpoint"].values:
            return None
        da = da.sel(setpoint=setpoint)
    return float(da.sel(row=r, col=c))


def _manifest_of(ds, manifest=None):
    method = ds.attrs.get("method", "?")
    text = str(manifest) if manifest is not None else str(ds.attrs.get("manifest_path", ""))
    if not text:
        raise DataUnavailable(
            f"the {method} result records no manifest path, so its raw data cannot be found"
        )
    path = Path(text)
    if not path.is_file():
        raise DataUnavailable(
            f"{path}: manifest of the {method} result not found (moved or "
            "deleted?); the raw data cannot be read"
        )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # already reported by the calibration
        m = read_manifest(path)
    want = str(ds.attrs.get("manifest_sha256", ""))
    if want and m.content_hash != want:
        raise DataUnavailable(
            f"{path}: manifest has changed since the {method} calibration "
            f"(SHA-256 {m.content_hash[:12]}… ≠ {want[:12]}…)"
        )
    return m


def _pixel_series(ds, pixel, manifest=None):
    """Counts of one pixel in every acquisition the result used, with its fitted parameters."""
    m = _manifest_of(ds, manifest)
    r, c = pixel
    if r not in ds["row"].values or c not in ds["col"].values:
        raise OptionError(
            f"pixel ({r}, {c}) is not in the result (rows {int(ds.row[0])}–"
            f"{int(ds.row[-1])}, cols {int(ds.col[0])}–{int(ds.col[-1])})"
        )
    out = []
    for acq in m.acquisitions:
        label = acq.level if acq.level is not None else acq.name
        sp = float(acq.em_gain_setpoint)
        params = {
            k: _pick(ds, k, label, sp, r, c) for k in ("photoelectrons", "em_gain", "e_per_adu")
        }
        if any(v is None for v in params.values()):
            continue  # an acquisition the method did not use (e.g. 1× for gs-no1x)
        h = stats.histograms(acq.frames()[:, r : r + 1, c : c + 1], adc_max=m.adc_max)
        if h.n[0] < 2:
            continue  # every frame saturated: nothing to show
        keep = h.counts[0] > 0
        gof = _pick(ds, "gof_pvalue", label, sp, r, c)
        out.append(
            _PixelAcq(
                acq.name,
                sp,
                h.values[0][keep],
                h.counts[0][keep],
                int(h.n[0]),
                float(h.mean[0]),
                float(h.var[0]),
                float(acq.offset[r, c]),
                float(acq.read_noise[r, c]),
                params,
                np.nan if gof is None else gof,
            )
        )
    if not out:
        raise DataUnavailable(
            f"{m.path}: no acquisition of the manifest matches the {ds.attrs.get('method')} result"
        )
    return out


def _em_model(ds) -> dict:
    """The register model a result was fitted with, as keyword arguments of the noise model."""
    return {"em_model": noise.EMModel.from_attrs(ds.attrs) or noise.EMModel()}


def _model_pmf(a, k, model):
    """The fitted pmf of acquisition ``a`` at integer counts ``k``, or None if unusable."""
    p = a.params
    try:
        return noise.pmf(
            k, p["photoelectrons"], p["em_gain"], p["e_per_adu"], a.offset, a.read_noise, **model
        )
    except ValueError:  # NaN or out-of-range estimates (a pixel that did not converge)
        return None


# --------------------------------------------------------------------------------------
# (1) Histograms with the fitted pmf
# --------------------------------------------------------------------------------------
def histogram_figure(ds, pixel=None, *, log=False, manifest=None, max_bins=80):
    """Each acquisition's histogram of one pixel's counts with the fitted pmf over it.

    The data are re-read through the result's ``manifest_path`` (or ``manifest``); the
    model is :func:`emccdcal.model.noise.pmf` at the pixel's fitted photoelectrons, EM gain
    (1 → Poisson–normal) and φ, with the offset and read noise and the EM register model
    the fit used. Saturated
    frames (at the ADC maximum) are left out, as in the fit.

    Parameters
    ----------
    ds : xarray.Dataset
        A calibration result.
    pixel : (int, int), optional
        Sensor (row, col) index (pixel); default :func:`default_pixel`.
    log : bool, optional
        Logarithmic probability axis, to see the tails (default linear).
    manifest : str or Path, optional
        The manifest, when it is no longer where the result says.
    max_bins : int, optional
        Most bins per histogram (fewer, about 2√n, for n < 1600 frames); bins are whole
        numbers of ADU wide.

    Returns
    -------
    matplotlib.figure.Figure
        One panel per acquisition: counts S (ADU) against probability per ADU (1/ADU),
        the data as a filled histogram and the pmf at integer counts as a line.

    Raises
    ------
    DataUnavailable
        The manifest is missing, moved, or changed since the calibration.
    """
    pixel = default_pixel(ds) if pixel is None else tuple(int(v) for v in pixel)
    series = _pixel_series(ds, pixel, manifest)
    fig, axes = _panels(len(series), 3)
    for ax, a in zip(axes, series):
        lo, hi = int(a.values.min()), int(a.values.max())
        bins = min(max_bins, max(10, int(2 * math.sqrt(a.n))))  # fewer for few frames
        w = max(1, math.ceil((hi - lo + 1) / bins))
        nb = (hi - lo) // w + 1
        binned = np.bincount((a.values - lo) // w, weights=a.counts, minlength=nb)
        edges = lo - 0.5 + w * np.arange(nb + 1)
        ax.stairs(
            binned / (a.n * w),
            edges,
            fill=True,
            alpha=0.45,
            color="C0",
            label=f"data ({a.n} frames)",
        )
        pad = 0.1 * (hi - lo + 1)
        k = np.unique(np.linspace(max(0, lo - pad), hi + pad, 1500).round().astype(np.int64))
        p = _model_pmf(a, k, _em_model(ds))
        if p is not None:
            ax.plot(k, p, color="C3", lw=1.3, label="fitted pmf")
        title = f"{a.name}: set-point {format_setpoint(a.setpoint)}×"
        if np.isfinite(a.gof_pvalue):
            title += f", gof p = {a.gof_pvalue:.2g}"
        ax.set_title(title if p is not None else title + " (no usable fit)", fontsize=9)
        ax.set_xlabel("counts S (ADU)")
        ax.set_ylabel("probability (1/ADU)")
        if log:
            ax.set_yscale("log")
            ax.set_ylim(bottom=0.3 / (a.n * w))
        ax.legend(fontsize=7)
    fig.suptitle(
        f"{ds.attrs.get('method')}: counts of pixel (row {pixel[0]}, col {pixel[1]}) "
        f"with the fitted pmf{' (log scale)' if log else ''}",
        fontsize=11,
    )
    return fig


# --------------------------------------------------------------------------------------
# (2) Photon-transfer curve
# --------------------------------------------------------------------------------------
def photon_transfer_figure(ds, pixel=None, *, manifest=None):
    """The photon-transfer curve of one pixel with the mean–variance fit lines.

    Each acquisition is a point: its offset-subtracted mean ``⟨S⟩ − S0`` (ADU) against its
    variance above read noise ``Var(S) − σ²`` (ADU²), with their sampling standard errors.
    Solid lines are the mean–variance fits of :mod:`emccdcal.fit.mv` — through all 1×
    acquisitions (slope 1/φ, :func:`emccdcal.fit.mv.fit_mv_adu`) and per gain set-point with
    the result's φ (slope 2g/φ, :func:`emccdcal.fit.mv.fit_mv_gain`); dashed lines are the
    slopes of the result's own fitted model (:func:`emccdcal.model.noise.variance`). Where the
    two differ (e.g. 5×, where the excess-noise factor is below 2), the moment method and
    the likelihood disagree.

    Parameters
    ----------
    ds : xarray.Dataset
        A calibration result.
    pixel : (int, int), optional
        Sensor (row, col) index (pixel); default :func:`default_pixel`.
    manifest : str or Path, optional
        The manifest, when it is no longer where the result says.

    Returns
    -------
    matplotlib.figure.Figure
        One panel; log–log when the means span more than a decade.

    Raises
    ------
    DataUnavailable
        The manifest is missing, moved, or changed since the calibration.
    """
    pixel = default_pixel(ds) if pixel is None else tuple(int(v) for v in pixel)
    series = _pixel_series(ds, pixel, manifest)
    fig, (ax,) = _panels(1, 1, size=(6.0, 4.0), margins=(0.8, 0.3, 0.4, 0.55))
    mean = np.array([a.mean for a in series])
    var = np.array([a.var for a in series])
    n = np.array([a.n for a in series], dtype=float)
    s0 = np.array([a.offset for a in series])
    sig = np.array([a.read_noise for a in series])
    sp = np.array([a.setpoint for a in series])
    x, y = mean - s0, var - sig**2
    phi = series[0].params["e_per_adu"]
    for j, s in enumerate(np.unique(sp)):
        sel = sp == s
        xs, ys = x[sel], y[sel]
        label = f"{format_setpoint(s)}×"
        slope = None
        try:
            if s == 1.0:
                f = mv.fit_mv_adu(
                    mean[sel, None], var[sel, None], s0[sel, None], sig[sel, None], n[sel]
                )
                slope = 1.0 / float(f.e_per_adu[0])
                label += (
                    f": mean–variance φ = {float(f.e_per_adu[0]):.4g} ± "
                    f"{float(f.e_per_adu_se[0]):.2g} e⁻/ADU"
                )
            elif np.isfinite(phi):
                f = mv.fit_mv_gain(
                    mean[sel, None],
                    var[sel, None],
                    s0[sel, None],
                    sig[sel, None],
                    n[sel],
                    phi,
                    sp[sel],
                )
                g = float(f.em_gain[0, 0])
                slope = 2.0 * g / phi
                label += f": mean–variance g = {g:.4g} ± {float(f.em_gain_se[0, 0]):.2g}"
        except ValueError:  # no signal above the offset: no line
            pass
        color = f"C{j % 10}"
        ax.errorbar(
            xs,
            ys,
            xerr=np.sqrt(var[sel] / n[sel]),
            yerr=np.sqrt(2 * var[sel] ** 2 / (n[sel] - 1)),
            fmt="o",
            ms=4,
            color=color,
            label=label,
        )
        span = np.array([0.7 * xs.min(), 1.4 * xs.max()])
        if slope is not None and np.isfinite(slope):
            ax.plot(span, slope * span, color=color, lw=1.2)
        p = series[np.flatnonzero(sel)[0]].params
        args = (p["photoelectrons"], p["em_gain"], p["e_per_adu"], 0.0, 1.0)  # S0 0, σ 1 ADU
        try:
            model = (float(noise.variance(*args, **_em_model(ds))) - 1.0) / float(noise.mean(*args))
        except (ValueError, ZeroDivisionError):  # NaN or out-of-range estimates
            model = np.nan
        if np.isfinite(model):
            ax.plot(span, model * span, color=color, lw=1.2, ls="--")
    if x.min() > 0 and y.min() > 0 and x.max() / x.min() > 10:
        ax.set_xscale("log")
        ax.set_yscale("log")
    ax.plot([], [], color="0.3", lw=1.2, label="solid: mean–variance fit")
    fitted = f" (φ = {phi:.4g} e⁻/ADU)" if _estimated_phi(ds) else ""
    ax.plot(
        [],
        [],
        color="0.3",
        lw=1.2,
        ls="--",
        label=f"dashed: slope of the {ds.attrs.get('method')} fit{fitted}",
    )
    ax.set_xlabel("offset-subtracted mean ⟨S⟩ − S0 (ADU)")
    ax.set_ylabel("variance above read noise Var(S) − σ² (ADU²)")
    ax.set_title(
        f"{ds.attrs.get('method')}: photon transfer of pixel (row {pixel[0]}, col {pixel[1]})",
        fontsize=10,
    )
    ax.legend(fontsize=7)
    return fig


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


# --------------------------------------------------------------------------------------
# (6) Gain against set-point
# --------------------------------------------------------------------------------------
def gain_points(ds):
    """Measured gain per set-point: median over converged pixels and median per-pixel SE.

    Parameters
    ----------
    ds : xarray.Dataset
        A result with ``em_gain``.

    Returns
    -------
    setpoints, gain, gain_se : ndarray
        Set-points (dimensionless), gains and SEs (dimensionless), set-point 1 included.
    """
    conv = _conv(ds)
    sp = np.asarray(ds["setpoint"].values, dtype=float)

    def median(var, s):
        v = _converged_values(ds[var].sel(setpoint=s), conv)
        return np.median(v) if v.size else np.nan

    return (
        sp,
        np.array([median("em_gain", s) for s in sp]),
        np.array([median("em_gain_se", s) for s in sp]),
    )


def gain_figure(results, *, labels=None):
    """Measured EM gain against the camera's set-point, with error bars and identity line.

    Parameters
    ----------
    results : sequence of xarray.Dataset
        Results; those without gains above 1× are skipped.
    labels : sequence of str, optional
        Legend labels (default: the methods).

    Returns
    -------
    matplotlib.figure.Figure
        Left: gain against set-point (log–log) with the line g = set-point. Right: the
        ratio g / set-point, where differences of a few per cent are visible. Points are
        medians over converged pixels, error bars the median per-pixel standard error.

    Raises
    ------
    DataUnavailable
        No result has a gain above 1×.
    """
    results = list(results)
    labels = _labels(results, labels)
    use = [(lab, ds) for lab, ds in zip(labels, results) if _gain_setpoints(ds)]
    if not use:
        raise DataUnavailable("no result has an EM gain above 1×: no gain curve to show")
    fig, (ax, ax2) = _panels(2, 2, size=(4.3, 3.2))
    allsp = []
    for j, (lab, ds) in enumerate(use):
        sp, g, se = gain_points(ds)
        allsp.extend(sp)
        kw = dict(fmt="o-", ms=4, capsize=3, color=f"C{j % 10}", label=lab)
        x = sp * (1 + 0.03 * (j - (len(use) - 1) / 2))  # dodge overlapping error bars
        ax.errorbar(x, g, yerr=se, **kw)
        ax2.errorbar(x, g / sp, yerr=se / sp, **kw)
    span = np.array([min(allsp), max(allsp)])
    ax.plot(span, span, color="k", ls=":", lw=1, label="g = set-point")
    ax2.axhline(1.0, color="k", ls=":", lw=1, label="g = set-point")
    for a, loc in ((ax, "upper left"), (ax2, "lower left")):
        a.set_xscale("log")
        a.set_xlabel(f"EM gain set-point {DIMLESS}")
        a.legend(fontsize=7, title=_SE_NOTE, title_fontsize=6, loc=loc)
    ax.set_yscale("log")
    ax.set_ylabel(f"measured EM gain g {DIMLESS}")
    ax2.set_ylabel(f"g / set-point {DIMLESS}")
    fig.suptitle("Measured EM gain against set-point", fontsize=11)
    return fig


def results_gain_curve_figure(results):
    """:func:`gain_curve_figure` of the gains of result datasets (the report's)."""
    from ..export.gain_curve import fit_points, measured_gains

    try:
        curve = fit_points(measured_gains(results))
    except OptionError as exc:
        raise DataUnavailable(f"no gain curve: {exc}") from None
    return gain_curve_figure(curve)


def gain_curve_figure(curve, *, predict=()):
    """The fitted gain curve (:mod:`emccdcal.export.gain_curve`) with its 95 % band.

    Parameters
    ----------
    curve : GainCurve
    predict : sequence of float
        Set-points predicted (marked on the curve).

    Returns
    -------
    matplotlib.figure.Figure
        Left: gain against set-point (log–log), the measured points with their SEs, the
        curve and its band. Right: the measured points' residuals from the curve, in %.
    """
    fig, (ax, ax2) = _panels(2, 2, size=(4.3, 3.2))
    lo, hi = curve.setpoints.min(), curve.setpoints.max()
    pred = [float(s) for s in predict]
    grid = np.geomspace(min([lo / 1.5, *pred]), max([hi * 1.5, *pred]), 200)
    p = curve.predict(grid)
    ax.fill_between(grid, p["lower"], p["upper"], color="C0", alpha=0.25, lw=0, label="95 % band")
    ax.plot(
        grid, p["gain"], color="C0", lw=1.2, label=f"curve (degree {curve.degree} in ln set-point)"
    )
    ax.errorbar(
        curve.setpoints,
        curve.gains,
        yerr=curve.gain_se,
        fmt="o",
        ms=4,
        capsize=3,
        color="k",
        label="measured (median over pixels)",
    )
    if pred:
        q = curve.predict(pred)
        ax.errorbar(
            q["setpoint"],
            q["gain"],
            yerr=1.96 * q["se_of_median"],
            fmt="s",
            ms=4,
            capsize=3,
            color="C3",
            label="predicted (95 %)",
        )
    at = curve.predict(curve.setpoints)
    ax2.errorbar(
        curve.setpoints,
        100 * (curve.gains / at["gain"] - 1),
        yerr=100 * curve.gain_se / at["gain"],
        fmt="o",
        ms=4,
        capsize=3,
        color="k",
    )
    ax2.fill_between(
        grid,
        100 * (p["lower"] / p["gain"] - 1),
        100 * (p["upper"] / p["gain"] - 1),
        color="C0",
        alpha=0.25,
        lw=0,
    )
    ax2.axhline(0, color="C0", lw=1)
    for a in (ax, ax2):
        a.set_xscale("log")
        a.set_xlabel(f"EM gain set-point {DIMLESS}")
    ax.set_yscale("log")
    ax.set_ylabel(f"EM gain g {DIMLESS}")
    ax2.set_ylabel("measured / curve − 1 (%)")
    ax.legend(fontsize=7, loc="upper left")
    fig.suptitle(f"Gain curve (chi2 = {curve.chi2:.3g} on {curve.dof} dof)", fontsize=11)
    return fig


def gain_check_figure(check):
    """The dark frames of a gain check: their counts about each pixel's offset, pooled
    over the pixels, with the fitted model's, on a log scale.

    Parameters
    ----------
    check : emccdcal.fit.darkgain.GainCheck

    Returns
    -------
    matplotlib.figure.Figure
    """
    h = check.histogram
    if not h:
        raise DataUnavailable("the gain check holds no histogram")
    offsets = np.asarray(h["offset_adu"], dtype=float)
    observed, expected = np.asarray(h["observed"]), np.asarray(h["expected"])
    fig, (ax,) = _panels(1, 1, size=(6.0, 3.4))
    shown = observed > 0
    ax.step(
        offsets[shown],
        observed[shown],
        where="mid",
        color="0.4",
        lw=0.8,
        label="dark counts, all pixels",
    )
    keep = expected > 0.1
    ax.plot(
        offsets[keep],
        expected[keep],
        color="C3",
        lw=1.2,
        label=f"fit: g = {check.em_gain:.4g} ± {check.em_gain_se:.2g}",
    )
    # the read-out alone (no event): what stands above it is the multiplied electrons
    sigma = check.read_noise
    width = float(np.median(np.diff(offsets))) if offsets.size > 1 else 1.0  # ADU a bin
    gauss = width * np.exp(-0.5 * (offsets / sigma) ** 2) / (np.sqrt(2 * np.pi) * sigma)
    readout = observed.sum() * gauss
    near = keep & (readout >= 0.5)
    ax.plot(offsets[near], readout[near], color="C0", lw=0.8, ls="--", label="read-out alone")
    ax.set_yscale("log")
    ax.set_ylim(0.5, 3.0 * max(float(observed.max()), 1.0))  # the data's range, not a model's
    ax.set_xlabel("count − pixel's offset (ADU)")
    ax.set_ylabel("frames × pixels (1)")
    ax.legend(fontsize=7)
    setpoint = "" if check.setpoint is None else f" at set-point {format_setpoint(check.setpoint)}x"
    ax.set_title(
        f"EM gain from dark frames{setpoint}: {check.events:.0f} events\n"
        f"{check.pixels} px × {check.frames} frames ({check.em_model})",
        fontsize=9,
    )
    return fig


def gain_history_figure(found, *, camera="", checks=()):
    """A camera's gain at each set-point against the date (database entries and checks).

    Parameters
    ----------
    found : sequence of emccdcal.export.database.Entry
        Calibrations, oldest first.
    checks : sequence of emccdcal.export.database.CheckEntry
        Gain checks from dark frames, drawn with open markers.

    Returns
    -------
    matplotlib.figure.Figure
        One panel per set-point: the sensor's gain (median over pixels) with the SE of
        that median, and each check's gain with its SE, relative to the first calibration,
        in %; one line per register model (calibrations under different models are not a
        change of the register).
    """
    import datetime as _dt

    def when(text):
        return _dt.datetime.fromisoformat(text.replace("Z", "+00:00"))

    setpoints = sorted({s for e in found for s in e.gains} | {c.setpoint for c in checks})
    if not setpoints:
        raise DataUnavailable("no calibration in the database has a gain above 1x")
    fig, axes = _panels(len(setpoints), 2, size=(4.0, 2.6))
    for ax, s in zip(axes, setpoints):
        have = [e for e in found if s in e.gains]
        checked = [c for c in checks if c.setpoint == s]
        first = have[0].gains[s][0] if have else checked[0].em_gain
        models = sorted({e.register for e in have} | {c.register for c in checked})
        for k, model in enumerate(models):
            mine = [e for e in have if e.register == model]
            label = f"{model} register" if len(models) > 1 else "calibration"
            if mine:
                g = np.array([e.gains[s][0] for e in mine])
                se = np.array([e.gains[s][1] or 0.0 for e in mine])
                ax.errorbar(
                    [when(e.date) for e in mine],
                    100 * (g / first - 1),
                    yerr=100 * se / first,
                    fmt="os^v"[k % 4] + "-",
                    ms=4,
                    capsize=3,
                    label=label,
                )
            theirs = [c for c in checked if c.register == model]
            if theirs:
                g = np.array([c.em_gain for c in theirs])
                se = np.array([c.se for c in theirs])
                ax.errorbar(
                    [when(c.date) for c in theirs],
                    100 * (g / first - 1),
                    yerr=100 * se / first,
                    fmt="Ds^v"[k % 4],
                    ms=5,
                    mfc="none",
                    capsize=3,
                    label=f"gain check ({model})"
                    if len(models) > 1
                    else "gain check (dark frames)",
                )
        if checked or len(models) > 1:
            ax.legend(fontsize=7)
        ax.axhline(0, color="k", lw=0.8, ls=":")
        ax.set_title(f"{format_setpoint(s)}x (first: g = {first:.4g})", fontsize=9)
        ax.set_ylabel("gain change (%)")
        for label in ax.get_xticklabels():
            label.set_rotation(30)
            label.set_fontsize(7)
    fig.suptitle(f"EM gain over time, camera {plain_text(camera)}", fontsize=11)
    return fig


# --------------------------------------------------------------------------------------
# (5) Beads (validation directories)
# --------------------------------------------------------------------------------------
def _sorted_keys(mapping):
    return sorted(mapping, key=float)


def _cal_label(cal, i):
    return plain_text(f"{cal.get('method', '?')} ({Path(str(cal.get('file', f'#{i + 1}'))).name})")


def bead_intensity_figure(directory, *, bead=0, bins=40):
    """Distributions of one bead's fitted intensity at each set-point, per calibration.

    Parameters
    ----------
    directory : str or Path
        A validation directory (:func:`read_validation`) with ``intensities.nc``.
    bead : int, optional
        Index of the bead along ``bead`` (default the first).
    bins : int, optional
        Histogram bins per panel (shared by its set-points).

    Returns
    -------
    matplotlib.figure.Figure
        One panel per calibration; one step histogram per set-point of the per-frame
        intensity (e⁻), its mean marked by a dashed line. Under a correct calibration the
        histograms coincide.

    Raises
    ------
    DataUnavailable
        No ``intensities.nc`` in the directory.
    """
    doc, da = read_validation(directory)
    if da is None:
        raise DataUnavailable(
            f"{Path(directory) / INTENSITIES_FILE}: no such file; the "
            "per-frame bead intensities are needed for their distributions"
        )
    cals = doc["calibrations"]
    if not 0 <= bead < da.sizes["bead"]:
        raise OptionError(f"bead {bead} out of range: {da.sizes['bead']} beads")
    fig, axes = _panels(len(cals), 3)
    sps = (
        np.asarray(da["setpoint"].values, dtype=float)
        if "setpoint" in da.coords
        else np.arange(da.sizes["setpoint"], dtype=float)
    )
    for i, (ax, cal) in enumerate(zip(axes, cals)):
        vals = np.asarray(da.isel(calibration=i, bead=bead).values, dtype=float)  # (S, F)
        fin = vals[np.isfinite(vals)]
        edges = np.histogram_bin_edges(fin, bins=bins) if fin.size else bins
        for j, s in enumerate(sps):
            v = vals[j][np.isfinite(vals[j])]
            ax.hist(
                v,
                bins=edges,
                histtype="step",
                lw=1.4,
                color=f"C{j % 10}",
                label=f"{format_setpoint(s)}×: mean {v.mean():.4g}" if v.size else None,
            )
            if v.size:
                ax.axvline(v.mean(), color=f"C{j % 10}", ls="--", lw=0.9)
        b = cal["beads"][bead] if bead < len(cal["beads"]) else {}
        where = f" at (row {b['row']:.4g}, col {b['col']:.4g})" if "row" in b else ""
        ax.set_title(f"{_cal_label(cal, i)}: bead {bead}{where}", fontsize=8)
        ax.set_xlabel(f"fitted bead intensity ({E_UNIT})")
        ax.set_ylabel("frames (count)")
        ax.legend(fontsize=6, title=f"set-point: mean ({E_UNIT})", title_fontsize=6)
    fig.suptitle("Bead intensities per set-point", fontsize=11)
    return fig


def bead_consistency_figure(directory):
    """Per-bead mean intensities relative to 1×, and the consistency metric per calibration.

    Parameters
    ----------
    directory : str or Path
        A validation directory (:func:`read_validation`); only ``validation.json`` is
        needed.

    Returns
    -------
    matplotlib.figure.Figure
        Left: for each calibration, the mean over beads of each bead's mean intensity at a
        set-point divided by its mean at 1× (the lowest set-point if there is no 1×), with
        the SD over beads as error bars; 1 is perfect consistency. Right: the metrics
        ``sigma_means_incl_1x`` and ``sigma_means_excl_1x`` of each calibration (the SD of a
        bead's per-set-point means scaled to its 1× mean, averaged over beads as
        ``validation.json`` reports them).
    """
    doc, _ = read_validation(directory)
    cals = doc["calibrations"]
    fig, (ax, ax2) = _panels(2, 2, size=(4.3, 3.2), gap=(1.0, 0.95), margins=(0.8, 0.3, 0.65, 1.05))
    for i, cal in enumerate(cals):
        ratios = {}
        for b in cal["beads"]:
            m = {k: v for k, v in b["mean_intensity"].items() if v is not None}  # null: no data
            keys = _sorted_keys(m)
            ref = "1" if "1" in m else (keys[0] if keys else None)
            for k in keys if ref is not None and m[ref] else ():
                ratios.setdefault(float(k), []).append(m[k] / m[ref])
        sp = np.array(sorted(ratios))
        r = [np.asarray(ratios[s], dtype=float) for s in sp]
        ax.errorbar(
            sp * (1 + 0.03 * (i - (len(cals) - 1) / 2)),  # dodge overlapping bars
            np.array([v.mean() for v in r]),
            yerr=np.array([v.std(ddof=1) if v.size > 1 else 0.0 for v in r]),
            fmt="o-",
            ms=4,
            capsize=3,
            color=f"C{i % 10}",
            label=_cal_label(cal, i),
        )
    ax.axhline(1.0, color="k", ls=":", lw=1)
    ax.set_xscale("log")
    ax.set_xlabel(f"EM gain set-point {DIMLESS}")
    ax.set_ylabel(f"bead mean intensity / 1× mean {DIMLESS}")
    ax.set_title("mean over beads ± SD over beads", fontsize=9)
    ax.legend(fontsize=6)
    pos = np.arange(len(cals))
    for off, key, lab in (
        (-0.2, "sigma_means_incl_1x", "with 1×"),
        (0.2, "sigma_means_excl_1x", "without 1×"),
    ):
        vals = [np.nan if c.get(key) is None else float(c[key]) for c in cals]
        ax2.bar(pos + off, vals, width=0.4, label=lab)
    ax2.set_xticks(
        pos, [_cal_label(c, i) for i, c in enumerate(cals)], rotation=30, ha="right", fontsize=7
    )
    ax2.set_xlabel("calibration (method)")
    ax2.set_ylabel(f"σ of means / 1× mean {DIMLESS}")
    ax2.set_title("consistency metric (lower is better)", fontsize=9)
    ax2.legend(fontsize=7)
    fig.suptitle("Bead consistency across set-points", fontsize=11)
    return fig


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


def write_validation_figures(out, *, beads=None):
    """Write the bead figures of a validation directory: intensity distributions, consistency.

    Uses :func:`bead_intensity_figure` (one figure per bead, up to ``beads``; default all)
    and :func:`bead_consistency_figure`.

    Returns
    -------
    list of Path
        The PNG files written (an SVG beside each).
    """
    out = Path(out)
    written = [save_figure(bead_consistency_figure(out), out / "bead_consistency")[0]]
    _, da = read_validation(out)
    n = da.sizes["bead"] if beads is None else min(int(beads), da.sizes["bead"])
    for b in range(n):
        written.append(
            save_figure(bead_intensity_figure(out, bead=b), out / f"bead_intensities_{b}")[0]
        )
    return written
