"""The EM gain: against its set-point (:func:`gain_figure`), the fitted gain curve, a gain check from dark frames, and a camera's history."""

from __future__ import annotations


import numpy as np

from ..._output import plain_text
from ...errors import OptionError
from ...result import format_setpoint
from .common import (
    DIMLESS,
    DataUnavailable,
    _SE_NOTE,
    _conv,
    _converged_values,
    _gain_setpoints,
    _labels,
    _panels,
)


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
    from ...export.gain_curve import fit_points, measured_gains

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
