"""Benchmark: throughput of the batched noise-model evaluator (the engine's core).

One "pixel-evaluation" is the log-likelihood of one pixel's 5000-frame histogram at one
set-point, with its gradient by (E, scale) and the outer-product information: exactly
what the engine computes per pixel, per acquisition and per iteration. Measured for the
paper's five set-points (1/5/25/100/300, E = 370 e⁻, φ = 3.859 e⁻/ADU, σ = 15.5 ADU) on
blocks of 256 pixels (the window: the block's FFT length), and for the public
``noise.logpmf`` on a vector.

Run: ``.venv/bin/python benchmarks/bench_noise.py``
"""

from __future__ import annotations

import time

import numpy as np
from bench_calibrate import machine

from emccdcal.data import stats
from emccdcal.fit import engine
from emccdcal.model import noise
from emccdcal.simulate.camera import simulate_frames


def main():
    print(machine())
    print(time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    P, frames, E, phi, S0, sigma = 256, 5000, 370.0, 3.859, 587.0, 15.5
    gains = {1: 1.0, 5: 4.78, 25: 22.95, 100: 90.06, 300: 261.6}
    print(f"{'set-point':>10}{'window':>9}{'pixel-evals/s':>15}")
    total = 0.0
    for sp, g in gains.items():
        counts = simulate_frames(E, g, phi, S0, sigma, frames=frames, rows=16, cols=16, seed=sp)
        h = stats.histograms(counts)
        acq = engine.AcquisitionBlock(
            h.values, h.counts, np.full(P, S0), np.full(P, sigma), sp == 1, h.mean, h.var, h.n
        )
        scale = np.full(P, 1 / phi if sp == 1 else g / phi)
        args = (acq, [np.full(P, np.log(E)), np.log(scale)], 1)
        engine._acquisition_terms(*args)  # warm-up
        reps = 5
        t0 = time.perf_counter()
        for _ in range(reps):
            engine._acquisition_terms(*args)
        dt = (time.perf_counter() - t0) / reps
        total += dt
        window = engine._ModelAtData(acq, np.full(P, E), scale).n
        print(f"{sp:>9}x{window:>9}{P / dt:>15.0f}")
    print(f"{'all five':>10}{'':>9}{P / total:>15.0f}  (pixel-series evaluations/s)")
    k = np.arange(0, 40000)
    t0 = time.perf_counter()
    noise.logpmf(k, E, 261.6, phi, S0, sigma)
    print(f"noise.logpmf on {k.size} counts at 300x: {time.perf_counter() - t0:.3f} s")


if __name__ == "__main__":
    main()
