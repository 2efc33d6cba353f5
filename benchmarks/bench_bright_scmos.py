"""An sCMOS at the bright levels the planner picks: the time of its calibration and how
honest φ's errors are on its quiet pixels (0.6–1 e⁻ of read noise).

The levels and frames are what ``emccdcal plan --camera-kind scmos --e-per-adu 0.46
--read-noise 3 --offset 100 --target-se 3 --pixel-well 30000`` picks; 10 × 12 px, one
seed. Prints the wall time, the RMS of z = (φ − truth)/SE and the pixels beyond |z| = 4
(docs/benchmarks.md, "sCMOS pixels at bright levels").
"""

from __future__ import annotations

import tempfile
import time
import warnings

import numpy as np
import tifffile

import emccdcal
from emccdcal.simulate.cmos import simulate_cmos_series

LEVELS = (813.5, 1627.0, 3254.0, 6508.0, 13016.0, 26032.0)


def main():
    work = tempfile.mkdtemp()
    sim = simulate_cmos_series(
        work, kind="scmos", rows=10, cols=12, frames=360, dark_frames=50, read_noise_e=1.38,
        levels=LEVELS, seed=5, progress=False,
    )  # fmt: skip
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = emccdcal.calibrate(sim.manifest, progress=False, scheduler="threads", workers=1)
    seconds = time.perf_counter() - t0
    truth = tifffile.imread(sim.outdir / "truth-e_per_adu.tif")
    z = ((ds.e_per_adu.values - truth) / ds.e_per_adu_se.values)[ds.converged.values]
    print(f"{z.size} px in {seconds:.1f} s; RMS z of phi {np.sqrt(np.mean(z**2)):.2f}; "
          f"|z| > 4 at {int(np.sum(np.abs(z) > 4))} (max {np.abs(z).max():.1f})")  # fmt: skip


if __name__ == "__main__":
    main()
