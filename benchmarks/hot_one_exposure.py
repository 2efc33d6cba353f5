"""Hot pixels in a dark at one exposure: which ones the telegraph test flags.

A Huang-protocol series (``simulate_cmos_series(..., exposure_s=T)``) whose dark and
levels hold the dark current's signal (log-normal about ``--dark-current`` e⁻/s, a tenth
of the pixels 30 times hotter), times T. Without darks at a second exposure no dark
current is measured and ``hot`` is not made; a hot pixel's dark counts are then a Poisson
mixture, not one normal, and the test of one normal against two
(:func:`emccdcal.data.telegraph.telegraph_pixels`, 1 % false alarms) is what flags them.
Per setting: the hot pixels flagged, the others flagged, and the hot pixels' dark signal.
Only the manifest is read (the darks reduced), no fit.

Run: ``.venv/bin/python benchmarks/hot_one_exposure.py [--seeds 8]`` (a few seconds).
"""

from __future__ import annotations

import argparse
import tempfile
import warnings

import numpy as np
import tifffile

import emccdcal
from emccdcal.simulate.cmos import simulate_cmos_series


def one_setting(kind, dark_current, exposure_s, seeds, first_seed):
    """(hot flagged, hot, others flagged, others, the hot pixels' dark signals (e⁻))."""
    counts = np.zeros(4, dtype=int)
    signal = []
    for seed in range(first_seed, first_seed + seeds):
        with tempfile.TemporaryDirectory() as folder:
            sim = simulate_cmos_series(
                folder, kind=kind, rows=10, cols=10, frames=50, dark_frames=3000,
                dark_current=dark_current, exposure_s=exposure_s, hot_fraction=0.1,
                seed=seed, progress=False,
            )  # fmt: skip
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                flagged = emccdcal.read_manifest(sim.manifest).acquisitions[0].dark_telegraph
            hot = tifffile.imread(sim.outdir / "truth-hot.tif") > 0
            rate = tifffile.imread(sim.outdir / "truth-dark_current.tif")
        counts += [(flagged & hot).sum(), hot.sum(), (flagged & ~hot).sum(), (~hot).sum()]
        signal += list(rate[hot] * exposure_s)
    return (*counts, np.array(signal))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--first-seed", type=int, default=24)
    ap.add_argument("--dark-current", type=float, default=0.05)
    ap.add_argument("--exposures", default="0.2,1.0", help="s, comma-separated")
    args = ap.parse_args()
    print(
        "| camera | exposure (s) | median dark signal: others, hot (e-) | hot flagged "
        "| others flagged |"
    )
    print("|---|---|---|---|---|")
    for t in (float(x) for x in args.exposures.split(",")):
        hit, hot, other_hit, others, signal = one_setting(
            "scmos", args.dark_current, t, args.seeds, args.first_seed
        )
        print(
            f"| scmos | {t:g} | {args.dark_current * t:.3g}, {np.median(signal):.2f} "
            f"| {hit}/{hot} ({hit / hot:.2f}) | {other_hit}/{others} "
            f"({other_hit / others:.3f}) |"
        )


if __name__ == "__main__":
    main()
