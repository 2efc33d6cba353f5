"""The bead validation: intensities per calibration, their consistency, and the figures a validation writes."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..._output import plain_text
from ...beads.validation import INTENSITIES_FILE, read_validation
from ...errors import OptionError
from ...result import format_setpoint
from .common import DIMLESS, DataUnavailable, E_UNIT, _panels, save_figure


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
