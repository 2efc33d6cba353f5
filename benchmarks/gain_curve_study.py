"""The gain curve's predictions against gains that were measured but left out.

(1) Real data: the ProEM gain series of Ryan et al. (2021) (``../shared/data/lanl-proem``,
``gs``, gamma model): for each interior set-point (25×, 100×), the curve fitted to the
other multiplied set-points predicts it, against its measured value.
(2) Known truth: a simulated gain series (32 × 32 px, 2000 frames) whose true gains follow
a smooth curve through the paper's four gains (quadratic in ln set-point) at set-points
5, 25, 50, 100, 200, 300. The curve fitted to 5/25/100/300 predicts 50× and 200×, against
the truth and against ``gs``'s own estimates there.

Run: ``.venv/bin/python benchmarks/gain_curve_study.py [DATA_DIR]``
"""

from __future__ import annotations

import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from proem_register_models import DATA, manifest

from emccdcal import calibrate
from emccdcal.export.gain_curve import fit_gain_curve, measured_gains
from emccdcal.simulate.series import simulate_gain_series

PAPER = {5.0: 4.78, 25.0: 22.95, 100.0: 90.06, 300.0: 261.6}


def _quiet(f, *a, **k):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return f(*a, **k)


def leave_one_out(points, held):
    curve = fit_gain_curve([p for p in points if p[0] != held])
    p = curve.predict([held])
    (meas,) = [q for q in points if q[0] == held]
    z = (p["gain"][0] - meas[1]) / np.hypot(p["se_of_median"][0], meas[2])
    return p["gain"][0], p["se_of_median"][0], meas[1], meas[2], z, curve.degree


def main(data: Path) -> None:
    print(time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    if data.is_dir():
        with tempfile.TemporaryDirectory() as tmp:
            ds = _quiet(calibrate, manifest(data.resolve(), Path(tmp)), "gs")
        points = measured_gains([ds])
        full = fit_gain_curve(points)
        print(
            f"real ProEM, gs: all four set-points, degree {full.degree}, "
            f"chi2 {full.chi2:.2f} on {full.dof} dof"
        )
        for held in (25.0, 100.0):
            g, se, m, mse, z, deg = leave_one_out(points, held)
            print(
                f"  {held:g}x left out: predicted {g:.3f} ± {se:.3f} (degree {deg}), measured "
                f"{m:.3f} ± {mse:.3f}: {100 * (g / m - 1):+.2f} %, z = {z:+.2f}"
            )
    x = np.log(np.array(sorted(PAPER)))
    coef = np.polyfit(x, np.log([PAPER[s] for s in sorted(PAPER)]), 2)
    setpoints = (1, 5, 25, 50, 100, 200, 300)
    truth = {s: 1.0 if s == 1 else float(np.exp(np.polyval(coef, np.log(s)))) for s in setpoints}
    with tempfile.TemporaryDirectory() as tmp:
        sim = simulate_gain_series(
            Path(tmp) / "gs",
            rows=32,
            cols=32,
            frames=2000,
            seed=17,
            setpoints=setpoints,
            em_gain=[truth[s] for s in setpoints],
        )
        ds = _quiet(calibrate, sim.manifest, "gs")
    points = measured_gains([ds])
    curve = fit_gain_curve([p for p in points if p[0] in PAPER])
    print(
        f"known truth: fitted to 5/25/100/300, degree {curve.degree}, chi2 {curve.chi2:.2f} "
        f"on {curve.dof} dof"
    )
    pred = curve.predict([50.0, 200.0])
    for i, s in enumerate((50.0, 200.0)):
        (meas,) = [p for p in points if p[0] == s]
        g, se = pred["gain"][i], pred["se_of_median"][i]
        print(
            f"  {s:g}x: predicted {g:.3f} ± {se:.3f} (95 % {pred['lower'][i]:.3f}–"
            f"{pred['upper'][i]:.3f}); truth {truth[s]:.3f} ({100 * (g / truth[s] - 1):+.2f} %,"
            f" {(g - truth[s]) / se:+.2f} SE); gs measured {meas[1]:.3f} ± {meas[2]:.3f}"
        )


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else DATA)
