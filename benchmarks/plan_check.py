"""The planner's predictions against what a calibration of the planned data reports.

For two cameras (the paper's ProEM-like camera: 3.859 e⁻/ADU, 15.5 ADU read noise,
offset 587.7 ADU, 16 bits; and a 16-bit camera with 12 e⁻/ADU and 40 ADU read noise) and
three targets (2, 1 and 0.5 % per pixel on every em_gain), ``emccdcal plan`` chooses the
light, the frames per set-point and the darks of a gain series (1, 5, 25, 100, 300×,
exact 536-stage register, the true gains the set-points); exactly that is simulated on
16 × 16 pixels and calibrated with ``gs``. Per plan: the predicted worst SE, the median
reported per-pixel SE and the scatter (SD of ln g over pixels), each as a ratio to the
prediction (worst over set-points), and the coverage of the 95 % intervals over the
4 × 256 gains; also the time ``plan`` took.

Run: ``.venv/bin/python benchmarks/plan_check.py [--seed 1]`` (about 10 minutes on a
2-core machine).
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np

from emccdcal.acquire.plan import plan
from emccdcal.calibration import calibrate
from emccdcal.simulate.series import simulate_gain_series

CAMERAS = {
    "ProEM-like (3.859 e-/ADU, 15.5 ADU)": dict(
        e_per_adu=3.859, read_noise=15.5, offset=587.7, adc_bits=16
    ),
    "16-bit (12 e-/ADU, 40 ADU)": dict(e_per_adu=12.0, read_noise=40.0, offset=500.0, adc_bits=16),
}
TARGETS = (2.0, 1.0, 0.5)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    print(
        "| camera | target | light (e-) | frames 1x/5x/25x/100x/300x | darks per set-point "
        "| plan (s) | predicted | reported / predicted | scatter / predicted | coverage |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, cam in CAMERAS.items():
        for target in TARGETS:
            t0 = time.perf_counter()
            p = plan(method="gs", setpoints=[1, 5, 25, 100, 300], target_se=target, **cam)
            took = time.perf_counter() - t0
            with tempfile.TemporaryDirectory() as tmp:
                sim = simulate_gain_series(
                    tmp,
                    setpoints=[a.setpoint for a in p.acquisitions],
                    em_gain=[a.em_gain for a in p.acquisitions],
                    photoelectrons=p.photoelectrons,
                    frames=[a.frames for a in p.acquisitions],
                    dark_frames=p.dark_frames,
                    seed=args.seed,
                    rows=16,
                    cols=16,
                    offset_drop=0.0,
                    e_per_adu=cam["e_per_adu"],
                    read_noise=cam["read_noise"],
                    offset=cam["offset"],
                )
                ds = calibrate(sim.manifest, method="gs", checks=False)
            reported, scatter, covered = [], [], []
            for a in p.acquisitions[1:]:
                g = ds.em_gain.sel(setpoint=a.setpoint).values.ravel()
                se = ds.em_gain_se.sel(setpoint=a.setpoint).values.ravel()
                pred = a.predicted_se["em_gain"] / 100
                reported.append(np.median(se / g) / pred)
                scatter.append(np.std(np.log(g)) / pred)
                covered.append(np.abs(g - a.em_gain) <= 1.96 * se)

            def span(x):
                return f"{min(x):.3f}–{max(x):.3f}"

            print(
                f"| {name} | {target:g} % | {p.photoelectrons:.0f} | "
                + "/".join(str(a.frames) for a in p.acquisitions)
                + f" | {p.dark_frames} | {took:.2f} | {p.predicted_se:.3f} % | "
                f"{span(reported)} | {span(scatter)} | {np.mean(covered):.3f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
