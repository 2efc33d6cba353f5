"""The gain from dark frames (``emccdcal gain-check``): accuracy, precision, flags, speed.

Parts (each prints a table; docs/gain-check.md holds the measured ones):

``grid``
    Known truth from the simulator (the exact 536-stage register, φ = 3.859 e⁻/ADU, offset
    500 ADU): gains 50-1000, clock-induced charge 0.001-0.02 e⁻/px/frame, read noise 20
    and 100 e⁻ rms, ``--pixels`` × ``--pixels`` px × ``--frames`` frames, ``--seeds``
    seeds a cell. Per cell: the mean and SD over seeds of z = (ĝ − g)/SE, the coverage of
    ĝ ± 1.96 SE, the median relative SE and the MLE's mean z (before the bias
    correction); also with register clock-induced charge (``--register-cic``, fitted).
``frames``
    The bias of the pixels' own parameters against the frames per pixel: the MLE and the
    corrected gain's mean relative error over seeds at a fixed number of pixel-frames.
``emccd-detect``
    Dark frames of NASA's emccd-detect (its 604-stage register, CIC 0.005 e⁻/px/frame
    before it, read noise 80 e⁻, 4 e⁻/ADU, 32 × 32 px × 4000 frames) at several gains.
``flags``
    A simulated gain series calibrated by ``gs``; then darks of the unchanged camera and
    of the camera after its gain fell 5 %, ``--seeds`` each: how often ``gain-check
    --calibration`` flags them (|z| > 3).
``speed``
    A 512 × 512 × 200-frame dark stack (300×, 0.005 e⁻/px/frame): wall time and peak
    memory of the check.

Run: ``.venv/bin/python benchmarks/gain_check_study.py PART [options]``.
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from emccdcal.fit.darkgain import check_gain
from emccdcal.simulate.camera import simulate_frames

PHI, OFFSET = 3.859, 500.0


def _z_stats(rows):
    z = np.array([(c.em_gain - g) / c.em_gain_se for c, g in rows])
    zm = np.array([(c.em_gain_mle - g) / c.em_gain_se for c, g in rows])
    se = np.median([c.relative_se for c, _ in rows])
    return z, zm, se


def grid(args) -> None:
    print(
        f"{args.pixels} x {args.pixels} px x {args.frames} frames, {args.seeds} seeds a "
        f"cell{', register CIC 0.005 fitted' if args.register_cic else ''}"
    )
    print(
        f"{'gain':>6} {'CIC':>6} {'σ e-':>5} {'σ ADU':>6} | {'z mean':>7} {'z SD':>5} "
        f"{'cover':>5} | {'rel SE':>7} | {'MLE z':>6} | {'s/check':>7}"
    )
    for g in (50.0, 100.0, 300.0, 1000.0):
        for cic in (0.001, 0.005, 0.02):
            for sigma_e in (20.0, 100.0):
                rows, t0, failed = [], time.perf_counter(), 0
                for seed in range(args.seeds):
                    darks = simulate_frames(
                        0.0,
                        g,
                        PHI,
                        OFFSET,
                        sigma_e / PHI,
                        frames=args.frames,
                        rows=args.pixels,
                        cols=args.pixels,
                        cic=cic,
                        register_cic=0.005 if args.register_cic else 0.0,
                        seed=seed,
                    )
                    try:
                        rows.append(
                            (check_gain([darks], PHI, fit_register_cic=args.register_cic), g)
                        )
                    except Exception as exc:  # too few events: the check refuses
                        failed += 1
                        note = type(exc).__name__
                if not rows:
                    print(
                        f"{g:>6g} {cic:>6g} {sigma_e:>5g} {sigma_e / PHI:>6.2f} | refused ({note})"
                    )
                    continue
                z, zm, se = _z_stats(rows)
                print(
                    f"{g:>6g} {cic:>6g} {sigma_e:>5g} {sigma_e / PHI:>6.2f} | "
                    f"{z.mean():>+7.2f} {z.std(ddof=1):>5.2f} {np.mean(np.abs(z) < 1.96):>5.2f} "
                    f"| {100 * se:>6.2f}% | {zm.mean():>+6.2f} | "
                    f"{(time.perf_counter() - t0) / args.seeds:>7.1f}"
                    + (f"  ({failed} refused)" if failed else ""),
                    flush=True,
                )


def frames(args) -> None:
    total = args.pixels * args.pixels * args.frames  # pixel-frames, kept for each row
    print(f"300x, 0.005 e-/px/frame, σ 15.5 ADU, {total} pixel-frames, {args.seeds} seeds")
    print(f"{'frames':>6} {'pixels':>7} | {'MLE bias':>9} {'corrected':>10} {'± (SE of mean)':>15}")
    for n in (100, 200, 400, 800, 1600):
        side = int(round(np.sqrt(total / n)))
        mle, jk = [], []
        for seed in range(args.seeds):
            darks = simulate_frames(
                0.0,
                300.0,
                PHI,
                OFFSET,
                15.5,
                frames=n,
                rows=side,
                cols=side,
                cic=0.005,
                seed=1000 + seed,
            )
            c = check_gain([darks], PHI)
            mle.append(c.em_gain_mle / 300 - 1)
            jk.append(c.em_gain / 300 - 1)
        sem = np.std(jk, ddof=1) / np.sqrt(len(jk))
        print(
            f"{n:>6} {side * side:>7} | {100 * np.mean(mle):>+8.2f}% {100 * np.mean(jk):>+9.2f}% "
            f"{100 * sem:>14.2f}%",
            flush=True,
        )


def emccd_detect(args) -> None:
    from emccd_detect.emccd_detect import EMCCDDetectBase

    print("emccd-detect darks: 32 x 32 px x 4000 frames, CIC 0.005, read noise 80 e-, 4 e-/ADU")
    print(f"{'gain':>6} | {'found':>16} {'z':>6} {'rel SE':>7} {'rate':>8}")
    for g in (100.0, 400.0, 1000.0):
        np.random.seed(args.seed)  # noqa: NPY002  (emccd-detect draws from NumPy's global generator)
        camera = EMCCDDetectBase(
            em_gain=g,
            full_well_image=1e5,
            full_well_serial=9e4,
            dark_current=0.0,
            cic=0.005,
            read_noise=80.0,
            bias=2000.0,
            qe=0.9,
            cr_rate=0.0,
            pixel_pitch=13e-6,
            eperdn=4.0,
            nbits=16,
            numel_gain_register=604,
        )
        darks = camera.sim_sub_frame(np.zeros((4000 * 32, 32)), 0.0).reshape(4000, 32, 32)
        c = check_gain([darks.astype(np.uint16)], 4.0, stages=604)
        print(
            f"{g:>6g} | {c.em_gain:>8.1f} ± {c.em_gain_se:>5.1f} "
            f"{(c.em_gain - g) / c.em_gain_se:>+6.2f} {100 * c.relative_se:>6.2f}% "
            f"{c.event_rate:>8.5f}",
            flush=True,
        )


def flags(args) -> None:
    from emccdcal import calibrate
    from emccdcal.export.gain_check import compare
    from emccdcal.result import load_calibration
    from emccdcal.simulate.series import simulate_gain_series

    with tempfile.TemporaryDirectory() as tmp:
        sim = simulate_gain_series(
            Path(tmp) / "gs",
            rows=16,
            cols=16,
            frames=400,
            dark_frames=3000,
            cic=0.02,
            setpoints=(1, 100, 300),
            em_gain=(1, 95, 310),
            seed=4,
            progress=False,
        )
        calibrate(sim.manifest, "gs", out=Path(tmp) / "cal", checks=False)
        cal = load_calibration(Path(tmp) / "cal")
        for label, g in (("unchanged", 310.0), ("fallen 5 %", 0.95 * 310.0)):
            flagged = 0
            for seed in range(args.seeds):
                darks = simulate_frames(
                    0.0,
                    g,
                    PHI,
                    587.7,
                    15.5,
                    frames=3000,
                    rows=16,
                    cols=16,
                    cic=0.02,
                    seed=10_000 + seed,
                )
                check = check_gain([darks], PHI, setpoint=300)
                flagged += compare(check, cal, z=3.0)["changed"]
            print(
                f"{label:>10}: flagged {flagged} of {args.seeds} "
                f"({100 * flagged / args.seeds:.1f} %)",
                flush=True,
            )


def speed(args) -> None:
    darks = simulate_frames(
        0.0, 300.0, PHI, OFFSET, 15.5, frames=200, rows=512, cols=512, cic=0.005, seed=args.seed
    )
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0 = time.perf_counter()
    c = check_gain([darks], PHI)
    seconds = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(
        f"512 x 512 x 200 frames: {seconds:.1f} s, {c.passes} passes; g = {c.em_gain:.2f} "
        f"± {c.em_gain_se:.2f} (truth 300; MLE {c.em_gain_mle:.2f}); peak memory "
        f"{peak:.0f} MiB ({before:.0f} MiB with the stack of {darks.nbytes / 2**20:.0f} MiB "
        "before the check)"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("part", choices=("grid", "frames", "emccd-detect", "flags", "speed"))
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--pixels", type=int, default=64)
    ap.add_argument("--frames", type=int, default=1000)
    ap.add_argument("--register-cic", action="store_true")
    args = ap.parse_args()
    {"grid": grid, "frames": frames, "emccd-detect": emccd_detect, "flags": flags, "speed": speed}[
        args.part
    ](args)


if __name__ == "__main__":
    main()
