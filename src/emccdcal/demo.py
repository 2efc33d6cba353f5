"""``emccdcal demo [DIR]``: the whole calibration of the paper on simulated data.

Simulates, with the paper's set-up and a fixed seed, a 1× intensity series (six levels)
and a gain series (set-points 1/5/25/100/300), then does what a user does with real
data: calibrates φ (e⁻/ADU) with ``is-adu``, then the true EM gains and the intensity
with ``gs`` using that φ, and prints truth against estimate ± standard error (medians
over pixels). Works offline; writes only into DIR (default: a new temporary directory),
including both results (``calibration.nc``, ``summary.json``) and — the command's default,
``report=True`` in Python — the HTML report of both (``report.html``,
:mod:`emccdcal.report.html`), whose path it prints last.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

from . import defaults
from .calibration import calibrate
from .result import format_setpoint
from .simulate.series import simulate_gain_series, simulate_intensity_series

__all__ = ["run_demo", "DEMO_SEED"]

#: Seed of the demo: the same numbers on every machine.
DEMO_SEED = defaults.DEMO_SEED


def _median(da):
    return float(np.nanmedian(np.asarray(da)))


def run_demo(
    outdir=None,
    *,
    rows=16,
    cols=16,
    frames=5000,
    multiplication=defaults.DEFAULT_EM_MODEL,
    seed=DEMO_SEED,
    progress=True,
    report=False,
    out=None,
    overwrite=False,
):
    """Simulate, calibrate φ then the gains, and print truth against estimate.

    Parameters
    ----------
    outdir : path, optional
        Where to write the series and the results (default: a new temporary directory,
        from which the simulated frames are removed at the end: the results and the
        report stay).
    rows, cols, frames : int, optional
        Size of each stack (default 16 × 16 px, 5000 frames).
    multiplication : {"cascade", "gamma"}, optional
        EM register of the simulated camera (default the exact cascade, a real
        camera's; ``"gamma"`` is the paper's simulations). The calibration uses the
        default register model, the cascade; the gains of the paper's gamma model on the
        same gain series are printed beside them.
    seed : int, optional
        Seed of the simulation.
    progress : bool, optional
        A progress bar (default): in a notebook or on a terminal; none in a pipe.
    report : bool, optional
        Also write ``DIR/report.html`` of both results (default False here; the
        ``emccdcal demo`` command writes it unless ``--no-report``).
    out : file, optional
        Where to print (default stdout).
    overwrite : bool, optional
        Replace the results of an earlier demo in ``outdir`` (once the new ones are
        complete).

    Returns
    -------
    dict
        ``adu`` and ``gs``: the two result datasets; ``outdir``: where everything is;
        ``report``: the HTML report (None without ``report``).
    """
    out = sys.stdout if out is None else out
    temporary = outdir is None
    outdir = Path(tempfile.mkdtemp(prefix="emccdcal-demo-") if temporary else outdir)
    common = dict(
        rows=rows, cols=cols, frames=frames, multiplication=multiplication, progress=progress
    )
    adu_sim = simulate_intensity_series(outdir / "adu-series", seed=seed, **common)
    gs_sim = simulate_gain_series(outdir / "gain-series", seed=seed + 1, **common)
    truth = gs_sim.truth
    print(
        f"emccdcal demo: {rows}×{cols} px, {frames} frames per acquisition, "
        f"{multiplication} multiplication, seed {seed}; files in {outdir}",
        file=out,
    )

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        adu = calibrate(
            adu_sim.manifest,
            "is-adu",
            out=outdir / "result-is-adu",
            progress=progress,
            overwrite=overwrite,
        )
        # φ chained from step 1 with its standard error, which the gains' errors include
        gs = calibrate(
            gs_sim.manifest,
            "gs",
            e_per_adu=outdir / "result-is-adu",
            out=outdir / "result-gs",
            progress=progress,
            overwrite=overwrite,
        )
        html = None
        if report:
            from .report.html import REPORT_FILE, write_report

            html = write_report(
                [outdir / "result-is-adu", outdir / "result-gs"],
                outdir / REPORT_FILE,
                progress=progress,
            )
    with warnings.catch_warnings():  # its misfit, if any, is not the calibration's
        warnings.simplefilter("ignore")
        # the paper's numbers are those of its gamma model: the same fit under it
        gs_paper = calibrate(
            gs_sim.manifest,
            "gs",
            e_per_adu=outdir / "result-is-adu",
            em_model=defaults.PAPER_EM_MODEL,
            checks=False,
        )

    _print_table(adu_sim.truth, truth, adu, gs, gs_paper, multiplication, out)
    print(f"  results: {outdir / 'result-is-adu'}, {outdir / 'result-gs'}", file=out)
    for w in dict.fromkeys(str(c.message) for c in caught):
        print(f"  warning: {w}", file=out)
    if html is not None:
        print(f"\nreport: {html}", file=out)
    if temporary:  # the simulated frames (tens of MB) go; the results and report stay
        for series in ("adu-series", "gain-series"):
            shutil.rmtree(outdir / series, ignore_errors=True)
        print(
            f"(the simulated frames were removed from {outdir}; 'emccdcal demo -o DIR' keeps them)",
            file=out,
        )
    return {"adu": adu, "gs": gs, "outdir": outdir, "report": html}


def _print_table(adu_truth, truth, adu, gs, gs_paper, multiplication, out) -> None:
    """The demo's table: truth against the estimates of both steps."""
    rows, cols = adu.sizes["row"], adu.sizes["col"]
    print("\nstep 1: ADU conversion factor from the 1x intensity series (is-adu)", file=out)
    header = f"  {'quantity':<28}{'truth':>12}{'estimate':>12}{'± SE':>10}"
    print(header, file=out)
    print(
        f"  {'e_per_adu (e-/ADU)':<28}{adu_truth['e_per_adu']:>12.4f}"
        f"{_median(adu.e_per_adu):>12.4f}{_median(adu.e_per_adu_se):>10.4f}",
        file=out,
    )
    for i, acq in enumerate(adu_truth["acquisitions"]):
        print(
            f"  {'photoelectrons ' + str(adu.level.values[i]) + ' (e-)':<28}"
            f"{acq['photoelectrons']:>12.1f}{_median(adu.photoelectrons[i]):>12.1f}"
            f"{_median(adu.photoelectrons_se[i]):>10.1f}",
            file=out,
        )

    print(
        f"\nstep 2: true EM gains from the gain series with that e_per_adu (gs, "
        f"{gs.attrs['em_model']} register of {gs.attrs['register_stages']} stages)",
        file=out,
    )
    header += f"{'gamma model':>13}"
    print(header, file=out)
    print(
        f"  {'photoelectrons (e-)':<28}{truth['acquisitions'][0]['photoelectrons']:>12.2f}"
        f"{_median(gs.photoelectrons):>12.2f}{_median(gs.photoelectrons_se):>10.2f}"
        f"{_median(gs_paper.photoelectrons):>13.2f}",
        file=out,
    )
    for acq in truth["acquisitions"]:
        sp = acq["em_gain_setpoint"]
        sel = gs.sel(setpoint=sp)
        print(
            f"  {'em_gain at ' + format_setpoint(sp) + 'x':<28}{acq['em_gain']:>12.3f}"
            f"{_median(sel.em_gain):>12.3f}{_median(sel.em_gain_se):>10.3f}"
            f"{_median(gs_paper.em_gain.sel(setpoint=sp)):>13.3f}",
            file=out,
        )
    print(
        f"\n  pixels converged: {int(adu.converged.sum())}/{rows * cols} in is-adu, "
        f"{int(gs.converged.sum())}/{rows * cols} in gs; "
        f"{adu.attrs['seconds'] + gs.attrs['seconds']:.1f} s of calibration",
        file=out,
    )
    print(
        "  (medians over pixels; the SEs of step 2 include that of e_per_adu from step 1;", file=out
    )
    print(
        f"  'gamma model': the paper's approximation of the register, --em-model gamma, "
        f"which reproduces the paper's numbers; this camera's register is "
        f"the {multiplication} model)",
        file=out,
    )
