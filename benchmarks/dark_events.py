"""Dark stacks with multiplied events: the read noise and offset by the noise-model fit
(:func:`emccdcal.data.dark.fit_dark`) against the plain per-pixel mean and SD.

A 604-stage register (φ 5.2 e⁻/ADU, σ 15.4 ADU, offset 500 ADU), 0.02 clock-induced
electrons per pixel per frame, 32 × 32 pixels, 2000 dark frames, at several set-points.
The truth of the read noise is the simulator's rounded read-out, sqrt(σ² + 1/12).

Run: ``.venv/bin/python benchmarks/dark_events.py``
"""

from __future__ import annotations

import time

import numpy as np

from emccdcal.data.dark import fit_dark, maps_from_dark
from emccdcal.simulate.camera import simulate_frames


def main():
    truth = np.sqrt(15.4**2 + 1 / 12)
    print(
        f"{'gain':>6} | {'σ fit':>8} {'σ mean/SD':>10} | {'S0 fit':>8} {'S0 mean':>8} | "
        f"{'rate':>7} {'θ ADU/e':>8} (g/φ) | {'s':>5}"
    )
    for g in (5.0, 20.0, 100.0, 400.0):
        dark = simulate_frames(
            0.0,
            g,
            5.2,
            500.0,
            15.4,
            frames=2000,
            rows=32,
            cols=32,
            cic=0.02,
            multiplication="cascade",
            stages=604,
            seed=7,
        )
        t0 = time.perf_counter()
        fit = fit_dark(dark)
        seconds = time.perf_counter() - t0
        offset, sd = maps_from_dark(dark)
        rate = np.nanmean(fit.event_rate) if fit.event_scale else float("nan")
        print(
            f"{g:>5g}x | {100 * (fit.read_noise.mean() / truth - 1):>+7.2f}% "
            f"{100 * (sd.mean() / truth - 1):>+9.2f}% | {fit.offset.mean() - 500:>+8.3f} "
            f"{offset.mean() - 500:>+8.3f} | {rate:>7.4f} {fit.event_scale:>8.2f} "
            f"({g / 5.2:.2f}) | {seconds:>5.1f}"
        )


if __name__ == "__main__":
    main()
