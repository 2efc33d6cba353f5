"""Benchmark: fitting 10 beads × 500 frames × 5 set-points, and its accuracy under the truth.

Simulates (once, into a temporary directory) the default bead movies of
``emccdcal simulate beads`` — 64 × 64 px, 10 beads of 5000 e⁻ per frame, width 1.3 px,
background 10 e⁻/px, set-points 1/5/25/100/300× with the paper's true gains, 500 frames
each, 2000-frame darks — then fits every bead in every frame under the true calibration
as ``emccdcal validate`` does (``emccdcal.beads.fit.fit_beads`` per acquisition with the
bead's shape shared by its frames, then again with each bead's width pooled over the
set-points, ``shared_widths``; the dark maps of the manifest) and reports for both passes:

* wall time per set-point and in all (target: ≤ 60 s), and the peak resident memory;
* the done-when figures of: per set-point, the mean over frames of each bead's
  intensity against the truth (pooled over beads and the worst bead; a bead's error is
  the frames' scatter and its offset map's error, ``--dark-frames``), and the RMS
  standard error against the scatter over frames.

``--photoelectrons``, ``--width`` and ``--background`` change the beads (the low-signal
cases: 3000 or 1000 e⁻, width 1.4 px, background 15 e⁻/px). ``--halo F`` gives the beads a
PSF the Gaussian does not describe (a fraction F of the light in a halo of SD
``--halo-width``), and a third pass adds each bead's oversampled residual image
(``residual_image``) to the model, as ``emccdcal validate --psf residual`` does; its
intensities are compared with the truth *within the box model*: the figures that matter
are the differences between set-points. ``--multiplication cascade`` simulates the exact register instead of the gamma model (the
fit still uses the paper's gamma model, so 5× shows the model mismatch).

Run: ``.venv/bin/python benchmarks/bench_beads.py [--multiplication cascade] [--seed 1]``
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from bench_calibrate import (
    machine,  # one description of the machine for every benchmark
)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--multiplication", choices=("gamma", "cascade"), default="gamma")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--frames", type=int, default=500)
    parser.add_argument(
        "--setpoints",
        default="1,5,25,100,300",
        help="comma-separated set-points (the paper's true gains)",
    )
    parser.add_argument(
        "--dark-frames",
        type=int,
        default=2000,
        help="frames of each dark stack the offset and read-noise maps come from",
    )
    parser.add_argument("--photoelectrons", type=float, default=5000.0, help="e- per bead")
    parser.add_argument("--width", type=float, default=1.3, help="PSF SD, px")
    parser.add_argument("--background", type=float, default=10.0, help="e-/px/frame")
    parser.add_argument("--halo", type=float, default=0.0, help="fraction of light in a halo")
    parser.add_argument("--halo-width", type=float, default=None, help="halo SD, px")
    parser.add_argument(
        "--pooled",
        action="store_true",
        help="one residual image for all beads (default one per bead)",
    )
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = parser.parse_args()
    from emccdcal import result
    from emccdcal.beads import fit as bead_fit
    from emccdcal.data.manifest import read_manifest
    from emccdcal.simulate.beads import simulate_beads

    print(machine())
    print(time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        sim = simulate_beads(
            Path(tmp) / "beads",
            multiplication=args.multiplication,
            frames=args.frames,
            dark_frames=args.dark_frames,
            seed=args.seed,
            setpoints=[float(v) for v in args.setpoints.split(",")],
            photoelectrons=args.photoelectrons,
            width=args.width,
            background=args.background,
            halo=args.halo,
            halo_width=args.halo_width,
        )
        print(
            f"simulated the bead movies ({args.multiplication}) in {time.perf_counter() - t0:.1f} s"
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            manifest = read_manifest(sim.manifest)
        truth = result.load(sim.outdir / "truth_calibration.nc")
        phi = truth["e_per_adu"].values
        t_all = time.perf_counter()
        acq0 = max(manifest.acquisitions, key=lambda a: a.em_gain_setpoint)
        t0 = time.perf_counter()
        found = bead_fit.detect_beads(acq0.frames(), acq0.offset)
        t_detect = time.perf_counter() - t0
        true_pos = np.array([[b["row"], b["col"]] for b in sim.truth["beads"]])
        true_n = np.array([b["photoelectrons"] for b in sim.truth["beads"]])
        # match found beads to the truth
        d = np.hypot(*(found.positions[:, None, :] - true_pos[None, :, :]).transpose(2, 0, 1))
        match = d.argmin(axis=1)
        acqs = manifest.acquisitions

        def fit_all(widths=None, residual=None):
            fits, times = [], []
            for acq in acqs:
                g = truth["em_gain"].sel(setpoint=acq.em_gain_setpoint).values
                t0 = time.perf_counter()
                fits.append(
                    bead_fit.fit_beads(
                        acq.frames(),
                        found.positions,
                        offset=acq.offset,
                        read_noise=acq.read_noise,
                        e_per_adu=phi,
                        em_gain=g,
                        adc_max=manifest.adc_max,
                        fixed_width=widths,
                        residual=residual,
                        offset_se=acq.read_noise / np.sqrt(acq.dark_frames),
                    )
                )
                times.append(time.perf_counter() - t0)
            return fits, times

        first, t_first = fit_all()
        widths = bead_fit.shared_widths(first)
        second, t_second = fit_all(widths)
        true_w = sim.truth["width"]
        print(
            f"shared widths: {np.round(widths, 4).tolist()} (truth {true_w}); per set-point "
            "widths of bead 0: "
            + ", ".join(f"{f.params[0, 0, 2]:.4f} ± {f.se[0, 0, 2]:.4f}" for f in first)
        )
        runs = [("width per set-point", first, t_first), ("width shared", second, t_second)]
        mismatch = {"width shared": [bead_fit.psf_mismatch(f) for f in second]}
        if args.halo > 0:
            image = bead_fit.residual_image(second, per_bead=not args.pooled)
            third, t_third = fit_all(widths, image)
            runs.append(("residual image", third, t_third))
            mismatch["residual image"] = [bead_fit.psf_mismatch(f) for f in third]
        for name, values in mismatch.items():
            print(
                f"PSF mismatch, {name}: chi2/pixel "
                + ", ".join(f"{v['chi2_per_pixel']:.2f}" for v in values)
                + "; missed in the box "
                + ", ".join(f"{100 * v['missed_fraction']:+.2f}%" for v in values)
            )
        passes = {}
        for name, fits, times in runs:
            rows = []
            for acq, fit, dt in zip(acqs, fits, times):
                ok = fit.converged
                N = np.where(ok, fit.intensity, np.nan)
                se = np.where(ok, fit.intensity_se, np.nan)
                n = ok.sum(axis=1)
                mean = np.nanmean(N, axis=1)
                sem = np.nanstd(N, axis=1, ddof=1) / np.sqrt(n)
                rel = mean / true_n[match] - 1
                # the bead's error: the frames' scatter and the offset map's error
                sem = np.hypot(sem, fit.intensity_offset_se)
                ratio = np.sqrt(np.nanmean(se**2, axis=1)) / np.nanstd(N, axis=1, ddof=1)
                pooled = np.nansum(N) / np.nansum(np.where(ok, true_n[match][:, None], np.nan)) - 1
                rows.append(
                    {
                        "setpoint": acq.em_gain_setpoint,
                        "seconds": dt,
                        "converged": float(ok.mean()),
                        "bias_pooled": float(pooled),
                        "bias_pooled_se": float(np.sqrt(np.sum(sem**2)) / np.sum(true_n[match])),
                        "bias_worst_bead": float(rel[np.argmax(np.abs(rel))]),
                        "bias_worst_bead_z": float(
                            (rel / (sem / true_n[match]))[np.argmax(np.abs(rel))]
                        ),
                        "se_over_scatter_mean": float(np.mean(ratio)),
                        "se_over_scatter_range": [float(ratio.min()), float(ratio.max())],
                        "retabulated": fit.retabulated,
                        "iterations": fit.iterations,
                    }
                )
            passes[name] = rows
        total = time.perf_counter() - t_all
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"beads found: {len(found.positions)} (detection {t_detect:.1f} s)")
    for name, rows in passes.items():
        print(f"{name}:")
        print(
            f"{'set-point':>9} {'s':>6} {'conv':>6} {'bias (pooled)':>16} {'worst bead':>18} "
            f"{'SE/scatter mean [min, max]':>28}"
        )
        for r in rows:
            print(
                f"{r['setpoint']:>8g}x {r['seconds']:6.1f} {r['converged']:6.3f} "
                f"{100 * r['bias_pooled']:+7.3f}% ± {100 * r['bias_pooled_se']:.3f}% "
                f"{100 * r['bias_worst_bead']:+7.3f}% ({r['bias_worst_bead_z']:+.1f} SE) "
                f"{r['se_over_scatter_mean']:8.3f} [{r['se_over_scatter_range'][0]:.3f}, "
                f"{r['se_over_scatter_range'][1]:.3f}]"
            )
    print(
        f"total fit time (detection + both passes over the set-points): {total:.1f} s; "
        f"peak memory {peak:.0f} MB"
    )
    if args.json is not None:
        args.json.write_text(
            json.dumps(
                {
                    "machine": machine(),
                    "multiplication": args.multiplication,
                    "seconds": total,
                    "peak_mb": peak,
                    "passes": passes,
                },
                indent=2,
            )
            + "\n"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
