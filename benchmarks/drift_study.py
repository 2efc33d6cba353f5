"""Study: false-alarm rate and power of the drift rule of the data-quality checks.

Every simulated calibration is the paper's gain series (set-points 1/5/25/100/300 at the
simulator's default true gains, E = 370 e⁻, φ = 3.859 e⁻/ADU, read noise 15.5 ADU, 5000
frames each) over a square region of P pixels, drawn with
:func:`emccdcal.simulate.camera.simulate_frames`. Its frame means, offset-subtracted, go
through :func:`emccdcal.data.quality.drift_test` at the family-wise level of the checks
(Bonferroni over the five acquisitions) — exactly what ``calibrate`` and ``check`` do.

* **False-alarm rate**: the fraction of steady calibrations with a drift finding in any
  acquisition (family-wise), with its 95 % Clopper–Pearson interval.
* **Power**: the fraction of acquisitions whose illumination drifts linearly by d over the
  acquisition (first to last frame) that are flagged, per region size and drift.

Run: ``.venv/bin/python benchmarks/drift_study.py [--steady 4000] [--drifting 400]
[--figure docs/figures/drift_study.png]``. Seeds are fixed (0, 1, 2, … per calibration).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from scipy import stats

from emccdcal.data.quality import DEFAULT_DRIFT_THRESHOLD, DRIFT_ALPHA, drift_test
from emccdcal.simulate.camera import DEFAULT_OFFSET, PAPER_SETPOINTS, simulate_frames
from emccdcal.simulate.series import default_em_gain

FRAMES = 5000
E = 370.0


def flags(side: int, drift: float, seed: int) -> list[bool]:
    """The drift finding of each acquisition of one simulated calibration."""
    alpha = DRIFT_ALPHA / len(PAPER_SETPOINTS)
    out = []
    for a, sp in enumerate(PAPER_SETPOINTS):
        stack = simulate_frames(
            E,
            em_gain=default_em_gain(sp),
            offset=DEFAULT_OFFSET,
            frames=FRAMES,
            rows=side,
            cols=side,
            drift=drift,
            seed=[seed, a],
        )
        means = stack.reshape(FRAMES, -1).mean(axis=1) - DEFAULT_OFFSET
        out.append(drift_test(means, alpha=alpha)["drifts"])
    return out


def clopper_pearson(k: int, n: int) -> tuple[float, float]:
    lo = stats.beta.ppf(0.025, k, n - k + 1) if k else 0.0
    hi = stats.beta.ppf(0.975, k + 1, n - k) if k < n else 1.0
    return float(lo), float(hi)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steady", type=int, default=4000, help="steady calibrations (3 × 3 px)")
    parser.add_argument(
        "--drifting", type=int, default=400, help="calibrations per region size and drift"
    )
    parser.add_argument("--sides", default="3,4,8", help="region sides, px")
    parser.add_argument("--drifts", default="0.0025,0.005,0.01", help="fractions")
    parser.add_argument("--figure", type=Path, default=None)
    args = parser.parse_args()
    print(time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    print(
        f"rule: |drift| ≥ {DEFAULT_DRIFT_THRESHOLD:g} % and p < {DRIFT_ALPHA:g} / "
        f"{len(PAPER_SETPOINTS)} (OLS t-test), E = {E:g} e⁻, {FRAMES} frames"
    )

    t0 = time.perf_counter()
    steady = [any(flags(3, 0.0, seed)) for seed in range(args.steady)]
    k = int(np.sum(steady))
    lo, hi = clopper_pearson(k, args.steady)
    print(
        f"false alarms, steady 3 x 3 px: {k} of {args.steady} calibrations = "
        f"{100 * k / args.steady:.2f} % (95 % CI {100 * lo:.2f}–{100 * hi:.2f} %), "
        f"{time.perf_counter() - t0:.0f} s"
    )

    sides = [int(s) for s in args.sides.split(",")]
    drifts = [float(d) for d in args.drifts.split(",")]
    power = {}
    for side in sides:
        for d in drifts:
            hits = np.array([flags(side, d, 10**6 + seed) for seed in range(args.drifting)])
            power[side, d] = hits.mean()
            lo, hi = clopper_pearson(int(hits.sum()), hits.size)
            print(
                f"power, {side} x {side} px, drift {100 * d:.2g} %: {100 * hits.mean():.1f} % "
                f"of {hits.size} acquisitions (95 % CI {100 * lo:.1f}–{100 * hi:.1f} %); "
                "by set-point " + ", ".join(f"{100 * h:.0f}" for h in hits.mean(axis=0))
            )

    if args.figure is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5, 3.4), layout="constrained")
        for side in sides:
            ax.plot(
                [100 * d for d in drifts],
                [100 * power[side, d] for d in drifts],
                "o-",
                label=f"{side} × {side} px",
            )
        ax.axhline(95, color="0.5", lw=0.8, ls="--")
        ax.axvline(0.5, color="0.5", lw=0.8, ls=":")
        ax.set_xlabel("linear drift over the acquisition (%)")
        ax.set_ylabel("acquisitions flagged (%)")
        ax.set_title(
            f"drift rule: false alarms {100 * k / args.steady:.2f} % of steady calibrations",
            fontsize=9,
        )
        ax.legend(fontsize=8)
        fig.savefig(args.figure, dpi=120)
        print(f"figure: {args.figure}")


if __name__ == "__main__":
    main()
