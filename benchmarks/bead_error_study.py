"""Are the bead means' error bars honest? Bead validation under the true calibration.

For ``--seeds`` seeds, beads are simulated (``emccdcal simulate beads``: 64 × 64 px, the
exact register, ``--beads`` beads of ``--photoelectrons`` e⁻, ``--frames`` frames at each
of ``--setpoints``) and validated under their true calibration (``emccdcal validate``,
as a user would). Each bead's mean intensity at each set-point is compared with the truth:
z = (mean − truth)/SE with the SE the validation reports (the frames' scatter, the offset
map's error and the bead's shared parameters' error) and with the SE before the shared
parameters' error was counted (scatter and offset map only). Printed per set-point and
over all: the mean and SD of the per-bead z, a Kolmogorov–Smirnov test of them against
the standard normal, and the RMS over set-points and seeds of the pooled (over beads)
mean's z. docs/beads.md holds the measured table.

Run: ``.venv/bin/python benchmarks/bead_error_study.py [--seeds 8] [--photoelectrons
3000 --beads 8 --frames 300]``.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from scipy import stats

from emccdcal.beads.validation import validate
from emccdcal.simulate.beads import TRUTH_CALIBRATION_FILE, simulate_beads


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--beads", type=int, default=8)
    ap.add_argument("--photoelectrons", type=float, default=3000.0)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--setpoints", default="1,5,25,100,300")
    args = ap.parse_args()
    setpoints = tuple(float(s) for s in args.setpoints.split(","))
    keys = [f"{s:g}" for s in setpoints]
    per = {k: {"old": [], "new": []} for k in keys}
    pooled = {"old": [], "new": []}
    by_bead = []  # each bead's z at every set-point (now): the z's of one bead share errors
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            sim = simulate_beads(
                Path(tmp) / f"b{seed}",
                seed=seed,
                beads=args.beads,
                photoelectrons=args.photoelectrons,
                frames=args.frames,
                setpoints=setpoints,
            )
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                doc = validate(
                    sim.manifest,
                    [str(sim.outdir / TRUTH_CALIBRATION_FILE)],
                    out=Path(tmp) / f"v{seed}",
                )
            truth = {
                (round(b["row"]), round(b["col"])): b["photoelectrons"] for b in sim.truth["beads"]
            }
            beads = doc["calibrations"][0]["beads"]
            for b in beads:
                true = min(
                    truth.items(),
                    key=lambda t: (t[0][0] - b["row"]) ** 2 + (t[0][1] - b["col"]) ** 2,
                )[1]
                by_bead.append(
                    [
                        np.nan
                        if b["mean_intensity"][k] is None
                        else (b["mean_intensity"][k] - true) / b["mean_intensity_se"][k]
                        for k in keys
                    ]
                )
            for k in keys:
                rows = []
                for b in beads:
                    true = min(
                        truth.items(),
                        key=lambda t: (t[0][0] - b["row"]) ** 2 + (t[0][1] - b["col"]) ** 2,
                    )[1]
                    mean, se = b["mean_intensity"][k], b["mean_intensity_se"][k]
                    shared = b["mean_intensity_se_shared"][k]
                    if mean is None or se is None:
                        continue
                    old = np.sqrt(max(se**2 - shared**2, 0.0))
                    rows.append((mean, true, old, se))
                    per[k]["old"].append((mean - true) / old)
                    per[k]["new"].append((mean - true) / se)
                m, t, old, new = (np.array(v) for v in zip(*rows))
                for name, e in (("old", old), ("new", new)):
                    pooled[name].append((m.mean() - t.mean()) / (np.sqrt(np.sum(e**2)) / e.size))
            print(f"seed {seed} done ({time.perf_counter() - t0:.0f} s)", flush=True)
    print(
        f"\n{args.seeds} seeds x {args.beads} beads of {args.photoelectrons:g} e-, "
        f"{args.frames} frames; z = (mean - truth)/SE; 'before': the frames' scatter and "
        "the offset map only"
    )
    print(
        f"{'set-point':>9} | {'before: z mean':>14} {'SD':>5} {'KS p':>7} | "
        f"{'now: z mean':>11} {'SD':>5} {'KS p':>7}"
    )
    summary = {}
    for k in keys + ["all"]:
        z = {
            n: np.array(sum((per[kk][n] for kk in keys), []) if k == "all" else per[k][n])
            for n in ("old", "new")
        }
        line = f"{k:>9} |"
        for n in ("old", "new"):
            p = stats.kstest(z[n], "norm").pvalue
            line += f" {z[n].mean():>+14.2f} {z[n].std(ddof=1):>5.2f} {p:>7.2g} |"
            summary.setdefault(k, {})[n] = {
                "mean": z[n].mean(),
                "sd": z[n].std(ddof=1),
                "ks_p": p,
                "n": int(z[n].size),
            }
        print(line.rstrip(" |"))
    for n in ("old", "new"):
        z = np.array(pooled[n])
        print(
            f"pooled means' z ({'before' if n == 'old' else 'now'}): RMS "
            f"{np.sqrt(np.mean(z**2)):.2f} over {z.size} (set-points x seeds), mean "
            f"{z.mean():+.2f}"
        )
    zb = np.array(by_bead)
    bead_mean = np.nanmean(zb, axis=1)
    corr = np.corrcoef(zb[np.all(np.isfinite(zb), axis=1)].T)
    off_diag = corr[~np.eye(len(keys), dtype=bool)]
    print(
        f"mean z over beads and set-points (now) {np.nanmean(zb):+.3f} ± "
        f"{bead_mean.std(ddof=1) / np.sqrt(bead_mean.size):.3f} (SE with each bead's "
        f"set-points as one cluster: they share its width's error; {bead_mean.size} beads); "
        f"mean correlation of a bead's z between set-points {off_diag.mean():+.2f}"
    )
    print(json.dumps({"per_setpoint": summary}, default=float))


if __name__ == "__main__":
    main()
