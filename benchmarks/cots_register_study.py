"""COTS on beads of an exact EM register, read through each register model's F².

For ``--seeds`` seeds, the default bead simulation (``emccdcal simulate beads``: 64 × 64
px, 10 beads of 5000 e⁻, 500 frames at each of 1 / 5 / 25 / 100 / 300×, the exact
536-stage Bernoulli cascade) is calibrated by ``emccdcal cots`` under the cascade and
under the gamma model (F² = 2, COTS as published). Per set-point and model: the mean
over all beads of ĝ/g − 1 with the SE of that mean, the mean and SD of the per-bead
z = (ĝ − g)/SE, and the coverage of ĝ ± 1.96 SE. docs/cots.md holds the measured table.

Run: ``.venv/bin/python benchmarks/cots_register_study.py [--seeds 8] [--work DIR]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from emccdcal import result
from emccdcal.beads.cots_calibration import cots_calibrate
from emccdcal.simulate.beads import TRUTH_CALIBRATION_FILE, simulate_beads

MODELS = ("cascade", "gamma")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument(
        "--photoelectrons",
        type=float,
        default=None,
        help="e- per bead per frame (default: the simulator's)",
    )
    ap.add_argument("--work", type=Path, default=None)
    args = ap.parse_args()
    rows = {m: {} for m in MODELS}  # model -> set-point -> [(g, se, truth)]
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            options = {} if args.photoelectrons is None else {"photoelectrons": args.photoelectrons}
            sim = simulate_beads(
                work / f"beads-{seed}", seed=seed, multiplication="cascade", **options
            )
            truth = result.load(sim.outdir / TRUTH_CALIBRATION_FILE)
            for model in MODELS:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    ds = cots_calibrate(sim.manifest, em_model=model)
                rr, cc = ds.bead_row.values, ds.bead_col.values
                for sp in ds.setpoint.values:
                    if sp == 1:
                        continue
                    g = ds.cots_em_gain.sel(setpoint=sp).values
                    se = ds.cots_em_gain_se.sel(setpoint=sp).values
                    true = truth.em_gain.sel(setpoint=sp).values[rr, cc]
                    ok = np.isfinite(g) & np.isfinite(se)
                    rows[model].setdefault(float(sp), []).extend(zip(g[ok], se[ok], true[ok]))
            print(f"seed {seed} done ({time.perf_counter() - t_start:.0f} s)", flush=True)
    print(
        f"\n{args.seeds} seeds, exact 536-stage cascade data"
        + ("" if args.photoelectrons is None else f", {args.photoelectrons:g} e- beads")
    )
    print(
        f"{'model':>8} {'set-point':>9} {'beads':>5} | {'mean g/g-1':>10} {'±':>6} | "
        f"{'z mean':>6} {'z SD':>5} {'cover':>5}"
    )
    for model in MODELS:
        for sp, vals in sorted(rows[model].items()):
            g, se, true = (np.array(v) for v in zip(*vals))
            rel = g / true - 1
            z = (g - true) / se
            print(
                f"{model:>8} {sp:>9g} {g.size:>5} | {100 * rel.mean():>+9.2f}% "
                f"{100 * rel.std(ddof=1) / np.sqrt(g.size):>5.2f}% | {z.mean():>+6.2f} "
                f"{z.std(ddof=1):>5.2f} {np.mean(np.abs(z) < 1.96):>5.2f}"
            )


if __name__ == "__main__":
    main()
