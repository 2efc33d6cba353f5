"""Known-truth study: per-pixel calibration of sCMOS and qCMOS cameras.

For each camera configuration (kind, median read noise in e⁻) and seed, simulates a
Huang-protocol series with per-pixel maps (:func:`emccdcal.simulate.cmos.simulate_cmos_series`:
a dark and four levels, ``--size`` square, ``--frames`` frames per level, twice as many
darks), calibrates it as a user would (``calibrate(manifest)``: the camera kind says
``is-adu``) and with Huang et al.'s per-pixel least squares of variance on mean
(``mv-adu``, the comparison method), and prints per configuration, pooled over seeds:

- φ: the mean z-score (bias in SEs), the RMS z, the 95 % intervals' coverage;
- the offset and the read-noise variance from the darks: mean z and RMS z (the analog σ
  where the model rounds, against the truth; the SE as the calibration's own);
- the goodness of fit: the fraction of pixel-levels at p < 0.01;
- the scatter (SD) of φ/true − 1 of the likelihood and of the least squares.

With ``--by-read-noise`` also φ's coverage by the pixel's true read noise (e⁻), where
the photon-number comb starts to show.

Run: ``.venv/bin/python benchmarks/cmos_study.py [--size 16] [--frames 1500]
[--seeds 3] [--first-seed 0] [--configs scmos:0.3,qcmos:0.27] [--by-read-noise]``.
Written up in docs/cmos.md.
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import tifffile

import emccdcal
from emccdcal.model import adc
from emccdcal.simulate.cmos import CMOSCamera, simulate_cmos_series

CONFIGS = [
    ("scmos", 0.3),
    ("scmos", 0.6),
    ("scmos", 1.4),
    ("scmos", 3.0),
    ("qcmos", 0.2),
    ("qcmos", 0.27),
    ("qcmos", 0.5),
]


def _maps_z(ds, truth_offset, truth_sigma, n_dark):
    """z-scores of the offset and of the read-noise variance from the darks."""
    offset = ds.offset.values[0].ravel()
    sigma = ds.read_noise.values[0].ravel()
    rounding = adc.rounds(True, sigma)
    # where the model does not round, the map is the dark counts' SD: σ² + 1/12
    var = np.where(rounding, sigma**2, sigma**2 - 1 / 12)
    off_var = np.where(rounding, 0.0, sigma**2 / n_dark)
    s_var = np.where(rounding, 0.0, sigma**2 / (2 * (n_dark - 1)))
    if rounding.any():
        cov = np.linalg.inv(adc.information(offset[rounding], sigma[rounding])) / n_dark
        off_var[rounding], s_var[rounding] = cov[:, 0, 0], cov[:, 1, 1]
    var_se = 2 * sigma * np.sqrt(s_var)  # of σ², by the delta method
    z_off = (offset - truth_offset.ravel()) / np.sqrt(off_var)
    z_var = (var - truth_sigma.ravel() ** 2) / var_se
    return z_off, z_var


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=16)
    ap.add_argument("--frames", type=int, default=1500)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=0, help="seeds first … first + seeds − 1")
    ap.add_argument("--configs", default=None, help="kind:read noise (e-), comma separated")
    ap.add_argument("--by-read-noise", action="store_true")
    ap.add_argument(
        "--dump", default=None, help="write each pixel's z, read noise (e-), phi, SE and truth "
        "per configuration to this .npz",
    )  # fmt: skip
    args = ap.parse_args()
    dumped = {}
    configs = CONFIGS
    if args.configs:
        configs = [(c.split(":")[0], float(c.split(":")[1])) for c in args.configs.split(",")]
    warnings.simplefilter("ignore")
    print(
        f"{args.size}x{args.size} px, {args.frames} frames per level, "
        f"{2 * args.frames} dark frames, {args.seeds} seeds per configuration"
    )
    head = (
        "kind   rn(e-) | phi: mean z  RMS z  cover95 | offset: mean z RMS z | "
        "var: mean z RMS z | GOF<0.01 | SD phi: ML    LSQ   ratio | s"
    )
    print(head)
    for kind, rn in configs:
        z_phi, z_off, z_var, gof, err_ml, err_ls, secs = [], [], [], [], [], [], 0.0
        noise_e, phis, ses, truths, seeds = [], [], [], [], []
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            camera = CMOSCamera(
                kind=kind, rows=args.size, cols=args.size, frames=args.frames,
                dark_frames=2 * args.frames, read_noise_e=rn,
            )  # fmt: skip
            with tempfile.TemporaryDirectory() as tmp:
                sim = simulate_cmos_series(
                    Path(tmp), camera=camera, seed=1000 * seed + 7, progress=False
                )
                t0 = time.perf_counter()
                ds = emccdcal.calibrate(sim.manifest, progress=False)
                secs += time.perf_counter() - t0
                ls = emccdcal.calibrate(sim.manifest, "mv-adu", progress=False)
                truth = {
                    k: tifffile.imread(sim.outdir / f"truth-{k}.tif")
                    for k in ("e_per_adu", "offset", "read_noise")
                }
            phi = ds.e_per_adu.values.ravel()
            t = truth["e_per_adu"].ravel()
            phis.append(phi)
            ses.append(ds.e_per_adu_se.values.ravel())
            truths.append(t)
            seeds.append(np.full(phi.size, seed))
            z_phi.append((phi - t) / ds.e_per_adu_se.values.ravel())
            noise_e.append(truth["read_noise"].ravel() * t)  # ADU × e-/ADU
            zo, zv = _maps_z(ds, truth["offset"], truth["read_noise"], 2 * args.frames)
            z_off.append(zo)
            z_var.append(zv)
            gof.append(ds.gof_pvalue.values.ravel())
            err_ml.append(phi / t - 1)
            err_ls.append(ls.e_per_adu.values.ravel() / t - 1)
        z, zo, zv = (np.concatenate(v) for v in (z_phi, z_off, z_var))
        sd_ml, sd_ls = np.std(np.concatenate(err_ml)), np.std(np.concatenate(err_ls))
        print(
            f"{kind:6s} {rn:5.2f} | {np.mean(z):+9.3f} {np.sqrt(np.mean(z**2)):6.3f} "
            f"{np.mean(np.abs(z) < 1.96):7.3f} | {np.mean(zo):+7.3f} {np.sqrt(np.mean(zo**2)):5.3f} | "
            f"{np.mean(zv):+7.3f} {np.sqrt(np.mean(zv**2)):5.3f} | "
            f"{np.mean(np.concatenate(gof) < 0.01):8.4f} | {sd_ml:.4f} {sd_ls:.4f} "
            f"{sd_ml / sd_ls:5.2f} | {secs / args.seeds:5.1f}",
            flush=True,
        )
        if args.dump:
            key = f"{kind}_{rn:g}"
            for name, values in (
                ("z", z_phi), ("read_noise_e", noise_e), ("phi", phis), ("phi_se", ses),
                ("phi_true", truths), ("seed", seeds),
            ):  # fmt: skip
                dumped[f"{key}_{name}"] = np.concatenate(values)
            np.savez(args.dump, **dumped)
        if args.by_read_noise:
            noise_e = np.concatenate(noise_e)
            edges = (0.0, 0.35, 0.5, 0.65, 0.8, 1.0, 1.5, np.inf)
            for lo, hi in zip(edges[:-1], edges[1:]):
                at = (noise_e >= lo) & (noise_e < hi)
                if at.any():
                    print(
                        f"    read noise {lo:.2f}-{hi:.2f} e-: {at.sum():4d} px, RMS z "
                        f"{np.sqrt(np.mean(z[at] ** 2)):5.2f}, cover95 "
                        f"{np.mean(np.abs(z[at]) < 1.96):.3f}",
                        flush=True,
                    )


if __name__ == "__main__":
    main()
