"""Corner plots of posterior samples (:func:`emccdcal.sample_posterior`).

matplotlib's object API only: no pyplot state, safe in scripts, servers and threads.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from .._output import atomic_write

__all__ = ["corner_figure", "write_corner_figures"]


def corner_figure(ds, pixel=0):
    """A corner plot of one pixel: 1-D histograms on the diagonal, 2-D hexbins below.

    Parameters
    ----------
    ds : xarray.Dataset
        A :func:`~emccdcal.sample_posterior` result.
    pixel : int
        Index along ``pixel``.

    Returns
    -------
    matplotlib.figure.Figure
    """
    n = int(ds.n_draws.values[pixel])
    s = ds.samples.values[pixel, :n]
    names = ds.parameter.values.tolist()
    units = ds.units.values.tolist()
    F = len(names)
    fig = Figure(figsize=(1.9 * F + 1, 1.9 * F + 1))
    axes = fig.subplots(F, F, squeeze=False)
    for i in range(F):
        for j in range(F):
            ax = axes[i, j]
            if j > i:
                ax.set_axis_off()
                continue
            if i == j:
                ax.hist(s[:, i], bins=40, color="0.3", histtype="step")
                for k, ls in (("median", "-"), ("q16", "--"), ("q84", "--")):
                    ax.axvline(float(ds[k].values[pixel, i]), color="C0", ls=ls, lw=0.8)
                mle = float(ds.mle.values[pixel, i])
                se = float(ds.mle_se.values[pixel, i])
                ax.axvline(mle, color="C3", lw=0.8)
                if np.isfinite(se):
                    ax.axvspan(mle - se, mle + se, color="C3", alpha=0.12)
                ax.set_yticks([])
            else:
                ax.hexbin(s[:, j], s[:, i], gridsize=25, cmap="Greys", mincnt=1)
            if i == F - 1:
                ax.set_xlabel(f"{names[j]}\n({units[j]})", fontsize=7)
            else:
                ax.set_xticklabels([])
            if j == 0 and i > 0:
                ax.set_ylabel(f"{names[i]}\n({units[i]})", fontsize=7)
            elif j > 0:
                ax.set_yticklabels([])
            ax.tick_params(labelsize=6)
    r, c = int(ds.row.values[pixel]), int(ds.col.values[pixel])
    fig.suptitle(
        f"{ds.attrs['method']} pixel ({r}, {c}): {n} draws; blue: median and 68 %, red: MLE ± SE",
        fontsize=9,
    )
    fig.tight_layout()
    return fig


def write_corner_figures(ds, out):
    """Write ``OUT/posterior_<row>_<col>.png`` for every pixel of a posterior result.

    Returns
    -------
    list of Path
        The files written.
    """
    written = []
    for i in range(ds.sizes["pixel"]):
        r, c = int(ds.row.values[i]), int(ds.col.values[i])
        png = Path(out) / f"posterior_{r}_{c}.png"
        atomic_write(png, lambda tmp, i=i: corner_figure(ds, i).savefig(tmp, dpi=100, format="png"))
        written.append(png)
    return written
