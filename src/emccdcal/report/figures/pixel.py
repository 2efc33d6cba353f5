"""One pixel's raw data against the fitted model: the histograms (:func:`histogram_figure`) and the photon transfer (:func:`photon_transfer_figure`)."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...data import stats
from ...data.manifest import read_manifest
from ...errors import OptionError
from ...model import adc
from ...fit import mv
from ...model import noise
from ...result import format_setpoint
from .common import DataUnavailable, _estimated_phi, _panels, default_pixel


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
    x, y = mean - s0, var - adc.count_variance(sig, sp == 1)  # σ analog where rounded
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
        args = (p["photoelectrons"], p["em_gain"], p["e_per_adu"], 0.0, 10.0)  # S0 0, σ 10 ADU
        try:
            model = (float(noise.variance(*args, **_em_model(ds))) - 100.0) / float(
                noise.mean(*args)
            )
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
