"""Known-truth study: bias and 95 % interval coverage of every method, two cameras.

The same simulations as ``tests/test_calibrate.py`` (32 × 32 = 1024 pixels, 2000 frames,
true offset and read-noise maps in the manifest), printed as a table for
``docs/validation.md``: for each method and parameter, the mean over pixels against the
truth (in units of the standard error of the mean, SEM), the median over all pixels and
whether the truth is in its 3σ order-statistic band, and the fraction of per-pixel 95 %
intervals that cover the truth. ``gs-hierarchical`` runs with the authors' hyperprior
scales in proportion to the camera's illumination (``hierarchical_options``: their 25 e⁻
on the paper's camera), and where that differs from their absolute 25 e⁻ also with
those. A last part runs ``gs-hierarchical`` where the illumination truly differs between
set-points.

Run: ``.venv/bin/python benchmarks/coverage_study.py [FIGURE.png]`` (the figure: the
coverage of every row, docs/figures/validation/coverage.png)
"""

from __future__ import annotations

import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

from emccdcal import calibrate
from known_truth import (
    CAMERAS,
    COLS,
    FRAMES,
    ROWS,
    STUDY_REGISTER,
    coverage,
    hierarchical_options,
    median_band,
    result_bounds,
    simulate_camera,
    truth_manifest,
)
from emccdcal.simulate.series import simulate_gain_series

#: The illumination at each set-point relative to 1× in the varying-illumination study.
ILLUMINATION_FACTORS = np.array([1.0, 1.04, 0.98, 1.02, 0.96])


def row(method, what, est, se, truth, bounds=None, undefined=None):
    """One table row: mean (± SEM), median over every pixel and interval coverage.

    The median ranks undefined estimates (NaN) at ``undefined`` (±inf: a mean–variance
    slope ≤ 0 means g below and E beyond any number); "in band" says whether the truth
    lies between the order statistics at ranks N/2 ± 3√N/2. Coverage uses the result's
    ``<name>_lower/_upper`` when it has them (Fieller for mean–variance; for
    gs-hierarchical those of the fit without the prior, printed beside the coverage of
    its MAP ± 1.96 SE and the ratio of the MAP's SD over pixels to its RMS SE), else
    ± 1.96 SE.
    """
    est, se = np.ravel(est), np.ravel(se)
    ok = np.isfinite(est) & np.isfinite(se)
    sem = est[ok].std(ddof=1) / np.sqrt(ok.sum())
    median, lo, hi = median_band(est, undefined)
    band = lo <= truth <= hi
    cover = coverage(est, se, truth, bounds)
    kind = "± 1.96 SE" if bounds is None else "Fieller" if method.startswith("mv") else "unpooled"
    ROWS_SEEN.append((ROWS_SEEN.section, method, what, cover, kind))
    note = ""
    if kind == "unpooled":  # the MAP's SE against its spread over pixels
        spread = est[ok].std(ddof=1) / np.sqrt(np.mean(se[ok] ** 2))
        note = f"; MAP ± 1.96 SE: {coverage(est, se, truth):.3f}, SD/SE {spread:.2f}"
    print(
        f"| {method} | {what} | {truth:g} | {est[ok].mean():.5g} ({(est[ok].mean() - truth) / sem:+.1f} SEM) "
        f"| {median:.5g} ({'in' if band else 'OUT of'} band) | {cover:.3f} ({kind}{note}) "
        f"| {ok.sum()} of {est.size} |"
    )


class _Rows(list):
    """(section, method, parameter, coverage, interval kind) of every row printed."""

    section = ""


#: what the figure shows
ROWS_SEEN = _Rows()


def header(title, short):
    ROWS_SEEN.section = short
    print(f"\n### {title}\n")
    print(
        "| method | parameter | truth | mean over defined pixels | median over all pixels "
        "| 95 % coverage | defined pixels |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- |")


def gain_series_rows(ds, method, cam, photoelectrons):
    for sp, g in zip(cam["setpoints"][1:], cam["em_gain"][1:]):
        s = ds.sel(setpoint=sp)
        row(
            method,
            f"em_gain {sp}x",
            s.em_gain.values,
            s.em_gain_se.values,
            g,
            result_bounds(ds, "em_gain", setpoint=sp),
            -np.inf,
        )
    pe = ds.photoelectrons
    if pe.ndim == 2:
        row(method, "photoelectrons", pe.values, ds.photoelectrons_se.values, photoelectrons[0])
        return
    for i, sp in enumerate(ds.setpoint.values):
        row(
            method,
            f"photoelectrons {sp:g}x",
            pe.values[i],
            ds.photoelectrons_se.values[i],
            photoelectrons[i],
            result_bounds(ds, "photoelectrons", setpoint=sp),
            np.inf,
        )


def main(figure=None):
    warnings.simplefilter("ignore")
    with tempfile.TemporaryDirectory() as tmp:
        for name, cam in CAMERAS.items():
            manifests = simulate_camera(Path(tmp) / name, cam)
            header(f"camera '{name}': {cam}", f"camera '{name}'")
            E = [cam["photoelectrons"]] * len(cam["setpoints"])
            options = hierarchical_options(cam)
            for method in ("gs", "gs-no1x", "gs-hierarchical", "mv-gain"):
                ds = calibrate(
                    manifests["gs"],
                    method,
                    options=options if method == "gs-hierarchical" else None,
                )
                gain_series_rows(ds, method, cam, E)
            if options["sigma_sd"] != 25.0:  # the authors' absolute scales as well
                ds = calibrate(manifests["gs"], "gs-hierarchical")
                gain_series_rows(ds, "gs-hierarchical (25 e-)", cam, E)
            for method in ("is-adu", "mv-adu"):
                ds = calibrate(manifests["adu"], method)
                row(
                    method,
                    "e_per_adu",
                    ds.e_per_adu.values,
                    ds.e_per_adu_se.values,
                    cam["e_per_adu"],
                    result_bounds(ds, "e_per_adu"),
                    np.inf,
                )
            for method in ("is-gain", "mv-gain"):
                ds = calibrate(manifests["isg"], method)
                sp = cam["is_gain_setpoint"]
                s = ds.sel(setpoint=sp)
                row(
                    method + " (IS)",
                    f"em_gain {sp}x",
                    s.em_gain.values,
                    s.em_gain_se.values,
                    cam["is_gain"],
                    result_bounds(ds, "em_gain", setpoint=sp),
                    -np.inf,
                )
        # gs-hierarchical where the illumination truly differs between set-points
        for name, cam in CAMERAS.items():
            E = list(cam["photoelectrons"] * ILLUMINATION_FACTORS)
            sim = simulate_gain_series(
                Path(tmp) / f"{name}-varying",
                setpoints=cam["setpoints"],
                em_gain=cam["em_gain"],
                photoelectrons=E,
                rows=ROWS,
                cols=COLS,
                frames=FRAMES,
                dark_frames=10,
                e_per_adu=cam["e_per_adu"],
                read_noise=cam["read_noise"],
                offset=cam["offset"],
                seed=31,
                multiplication=STUDY_REGISTER,
            )
            header(
                f"camera '{name}', illumination × {ILLUMINATION_FACTORS.tolist()} at "
                f"set-points {cam['setpoints']}",
                f"camera '{name}', E differs",
            )
            ds = calibrate(
                truth_manifest(sim, cam["read_noise"], STUDY_REGISTER),
                "gs-hierarchical",
                options=hierarchical_options(cam),
            )
            gain_series_rows(ds, "gs-hierarchical", cam, E)
    if figure is not None:
        figure.parent.mkdir(parents=True, exist_ok=True)
        coverage_figure(ROWS_SEEN).savefig(figure, dpi=110)
        print(f"\nwrote {figure}")


def coverage_figure(rows):
    """Coverage of every row, one panel per section, with the 93–97 % band."""
    from matplotlib.figure import Figure

    sections = list(dict.fromkeys(r[0] for r in rows))
    heights = [sum(r[0] == s for r in rows) for s in sections]
    fig = Figure(figsize=(7.5, 0.16 * sum(heights) + 1.2 * len(sections)), layout="constrained")
    axes = fig.subplots(len(sections), 1, height_ratios=heights, sharex=True, squeeze=False)[:, 0]
    colours = {
        "gs": "C0",
        "gs-no1x": "C1",
        "gs-hierarchical": "C3",
        "gs-hierarchical (25 e-)": "C8",
        "mv-gain": "C2",
        "is-adu": "C4",
        "mv-adu": "C5",
        "is-gain (IS)": "C6",
        "mv-gain (IS)": "C7",
    }
    for ax, section in zip(axes, sections):
        mine = [r for r in rows if r[0] == section]
        y = np.arange(len(mine))[::-1]
        ax.axvspan(0.93, 0.97, color="0.9", zorder=0)
        ax.axvline(0.95, color="0.5", lw=0.8)
        marker = {"± 1.96 SE": "o", "Fieller": "s", "unpooled": "^"}
        for yi, (_, method, what, cover, kind) in zip(y, mine):
            ax.plot(cover, yi, marker[kind], ms=4, color=colours.get(method, "k"))
        ax.set_yticks(y, [f"{m}: {w}" for _, m, w, _, _ in mine], fontsize=6)
        ax.set_title(section, fontsize=8, loc="left")
    axes[-1].set_xlabel(
        "fraction of 95 % intervals covering the truth\n(grey: 93–97 %; "
        "circles: ± 1.96 SE; squares: Fieller; triangles: no prior)",
        fontsize=8,
    )
    axes[-1].set_xlim(0.88, 1.0)
    return fig


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else None)
