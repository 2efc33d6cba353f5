"""Known-truth study: bias and 95 % interval coverage of every method, two cameras.

The same simulations as ``tests/test_calibrate.py`` (32 × 32 = 1024 pixels, 2000 frames,
true offset and read-noise maps in the manifest), printed as a table for
``docs/validation.md``: for each method and parameter, the mean and median over pixels
against the truth (in units of the standard error of the mean, SEM), and the fraction of
per-pixel 95 % intervals that cover the truth.

Run: ``.venv/bin/python benchmarks/coverage_study.py``
"""

from __future__ import annotations

import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_calibrate import CAMERAS, simulate_camera  # noqa: E402

from emccdcal.calibrate import calibrate  # noqa: E402


def row(method, what, est, se, truth):
    est, se = np.ravel(est), np.ravel(se)
    ok = np.isfinite(est) & np.isfinite(se)
    est, se = est[ok], se[ok]
    sem = est.std(ddof=1) / np.sqrt(est.size)
    cover = np.mean(np.abs(est - truth) <= 1.959964 * se)
    print(f"| {method} | {what} | {truth:g} | {est.mean():.5g} ({(est.mean() - truth) / sem:+.1f} SEM) "
          f"| {np.median(est):.5g} | {cover:.3f} | {ok.sum()} |")


def main():
    warnings.simplefilter("ignore")
    with tempfile.TemporaryDirectory() as tmp:
        for name, cam in CAMERAS.items():
            manifests = simulate_camera(Path(tmp) / name, cam)
            print(f"\n### camera '{name}': {cam}\n")
            print("| method | parameter | truth | mean over pixels | median | 95 % coverage | pixels |")
            print("| --- | --- | --- | --- | --- | --- | --- |")
            for method in ("gs", "gs-no1x", "gs-hierarchical", "mv-gain"):
                ds = calibrate(manifests["gs"], method)
                for sp, g in zip(cam["setpoints"][1:], cam["em_gain"][1:]):
                    s = ds.sel(setpoint=sp)
                    row(method, f"em_gain {sp}x", s.em_gain.values, s.em_gain_se.values, g)
                pe = ds.photoelectrons
                if pe.ndim == 2:
                    row(method, "photoelectrons", pe.values, ds.photoelectrons_se.values,
                        cam["photoelectrons"])
                else:
                    for i, sp in enumerate(ds.setpoint.values):
                        row(method, f"photoelectrons {sp:g}x", pe.values[i],
                            ds.photoelectrons_se.values[i], cam["photoelectrons"])
            for method in ("is-adu", "mv-adu"):
                ds = calibrate(manifests["adu"], method)
                row(method, "e_per_adu", ds.e_per_adu.values, ds.e_per_adu_se.values, cam["e_per_adu"])
            for method in ("is-gain", "mv-gain"):
                ds = calibrate(manifests["isg"], method)
                s = ds.sel(setpoint=cam["is_gain_setpoint"])
                row(method + " (IS)", f"em_gain {cam['is_gain_setpoint']}x", s.em_gain.values,
                    s.em_gain_se.values, cam["is_gain"])


if __name__ == "__main__":
    main()
