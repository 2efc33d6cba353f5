"""Bead data that the Gaussian fits of a stable bead do not describe, and what validate does.

Three simulated bead series (gamma register, the default camera, 10 beads of 5000 e⁻,
500 frames at each of 1/5/25/100/300×), each validated under the true calibration and
under one whose 25× gain is 2 % low (its 25× beads 2 % bright):

* ``blinking``: every bead off in 10 % of the frames, in runs of 5 on average
  (``simulate beads --blinking 0.1``), validated with ``--blinking ignore`` and
  ``--blinking model``; also the off frames found against the truth's;
* ``halo``: a PSF with 20 % of its light in a halo of 3× the width
  (``--halo 0.2``), validated with ``--psf gaussian`` and ``--psf residual``; also the
  Gaussian's χ² per pixel of the mean images;
* ``repeat``: a 2 % fade over the series with 1× recorded again at the end
  (``--bleaching 0.02 --repeat 1``), validated with the default ``--bleaching correct``.

Prints, per scenario and option, the metric (σ incl 1×, mean over beads) of both
calibrations, the ranking, and each set-point's mean bead intensity over the 1× mean
under the truth. Writes the figures to ``--json`` if given.

Run: ``.venv/bin/python benchmarks/bead_artefacts.py [--seed 3] [--json out.json]``
(about 15 minutes on a 2-core machine).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from bench_calibrate import machine

SCENARIOS = {
    "blinking": ({"blinking": 0.1}, [{"blinking": "ignore"}, {"blinking": "model"}]),
    "halo": ({"halo": 0.2}, [{"psf": "gaussian"}, {"psf": "residual"}]),
    "repeat": ({"bleaching": 0.02, "repeat": 1}, [{}]),
}


def wrong_calibration(truth_file, out):
    """The truth with the 25× gain 2 % low."""
    from emccdcal import result

    ds = result.load(truth_file)
    gain = ds["em_gain"].copy()
    gain.loc[{"setpoint": 25.0}] = 0.98 * gain.sel(setpoint=25.0)
    ds = ds.assign(em_gain=gain)
    ds.attrs["method"] = "gs"
    result.save(ds, out)
    return out / result.CALIBRATION_FILE


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--frames", type=int, default=500)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--only", choices=list(SCENARIOS), nargs="+", default=list(SCENARIOS))
    args = parser.parse_args()
    from emccdcal.beads import validation
    from emccdcal.simulate.beads import simulate_beads

    print(machine())
    print(time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    out = {
        "machine": machine(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "seed": args.seed,
        "frames": args.frames,
        "scenarios": {},
    }
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.only:
            sim_options, runs = SCENARIOS[name]
            sim = simulate_beads(
                Path(tmp) / name, frames=args.frames, seed=args.seed, **sim_options
            )
            truth = sim.outdir / "truth_calibration.nc"
            wrong = wrong_calibration(truth, Path(tmp) / f"{name}-wrong")
            rows = []
            for options in runs:
                t0 = time.perf_counter()
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    doc = validation.validate(sim.manifest, [str(truth), str(wrong)], **options)
                seconds = time.perf_counter() - t0
                t, w = doc["calibrations"]
                rel = {
                    k: float(
                        np.mean(
                            [b["mean_intensity"][k] / b["mean_intensity"]["1"] for b in t["beads"]]
                        )
                    )
                    for k in doc["setpoints"]
                }
                row = {
                    "options": options,
                    "seconds": seconds,
                    "truth_sigma_incl_1x": t["sigma_means_incl_1x"],
                    "wrong_sigma_incl_1x": w["sigma_means_incl_1x"],
                    "truth_first": doc["ranking"][0] == str(truth),
                    "truth_relative_to_1x": rel,
                    "frames_off_found": sum(t["blinking"]["frames_off"].values()),
                    "psf_mismatch": t["psf_mismatch"],
                    "intensity_trend": t["intensity_trend"],
                    "repeats": t["repeats"],
                    "warnings": sorted({str(c.message) for c in caught}),
                }
                rows.append(row)
                print(f"\n{name} {options or '(defaults)'}: {seconds:.0f} s")
                print(
                    f"  sigma incl 1x: truth {100 * row['truth_sigma_incl_1x']:.3f} %, "
                    f"25x 2 % low {100 * row['wrong_sigma_incl_1x']:.3f} %; "
                    f"truth ranks first: {row['truth_first']}"
                )
                print(
                    "  truth, mean bead intensity / 1x mean: "
                    + ", ".join(f"{k}x {v:.4f}" for k, v in rel.items())
                )
                if name == "blinking":
                    true_off = sum(b["frames_off"] for b in sim.truth["beads"])
                    print(f"  frames off: found {row['frames_off_found']}, true {true_off}")
                    row["frames_off_true"] = true_off
                for model, per in t["psf_mismatch"].items():
                    print(
                        f"  chi2/pixel ({model}): "
                        + ", ".join(f"{k} {v['chi2_per_pixel']:.2f}" for k, v in per.items())
                    )
                if t["intensity_trend"]["detected"]:
                    tr = t["intensity_trend"]
                    print(
                        f"  trend: fade {100 * tr['fade_over_series']:.2f} % "
                        f"(z {tr['z']:.1f}), corrected {tr['corrected']}"
                    )
                for r in t["repeats"]:
                    for later in r["later"]:
                        print(
                            f"  repeat {r['setpoint']}x: {later['acquisition']} / {r['first']}"
                            f" = {later['ratio']:.4f} ± {later['ratio_se']:.4f} "
                            f"(z {later['z']:.1f})"
                        )
            out["scenarios"][name] = {"simulation": sim_options, "runs": rows}
    if args.json is not None:
        args.json.write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
