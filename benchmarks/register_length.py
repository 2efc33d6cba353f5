"""How much the register's length matters: ``gs`` under the cascade at every length of
``STAGE_GRID``, on the real ProEM gain series and on a simulated 604-stage register.

For docs/cascade.md ("How long is the register?"). Prints, per length: the summed
log-likelihood relative to its maximum (nats), the median gain at each set-point relative
to that at 536 stages (the default), and for the simulation the median gain's error
against the truth; then the time of one ``gs`` under the gamma model and under the
default cascade, alternating, as a ratio.

Run: ``.venv/bin/python benchmarks/register_length.py [DATA_DIR]``
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
from emccdcal.calibration import STAGE_GRID
from emccdcal.simulate.series import simulate_gain_series

SIM = dict(rows=8, cols=8, frames=5000, seed=604, multiplication="cascade", stages=604)


def quiet(*args, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return calibrate(*args, **kw)


def profile(path, truth=None, **kw):
    lengths = sorted({*STAGE_GRID, 536})  # the grid of --stages auto and the default
    runs = {n: quiet(path, "gs", em_model="cascade", stages=n, **kw) for n in lengths}
    ll = {n: float(r.loglik.values.sum()) for n, r in runs.items()}
    best = max(ll.values())
    ref = runs[536]
    setpoints = ref.setpoint.values[1:]
    head = f"{'stages':>6} | {'Δ loglik':>9} | " + " ".join(
        f"{f'g {s:g}x / 536':>12}" for s in setpoints
    )
    if truth is not None:
        head += " | " + " ".join(f"{f'{s:g}x vs truth':>12}" for s in setpoints)
    print(head)
    for n, r in runs.items():
        g = np.median(r.em_gain.values[1:], axis=(1, 2))
        g0 = np.median(ref.em_gain.values[1:], axis=(1, 2))
        line = f"{n:>6} | {ll[n] - best:>9.2f} | " + " ".join(
            f"{x:>+11.3f}%" for x in 100 * (g / g0 - 1)
        )
        if truth is not None:
            line += " | " + " ".join(f"{x:>+11.3f}%" for x in 100 * (g / truth - 1))
        print(line)


def timing(path, repeat=3, **kw):
    times = {"gamma": [], "cascade": []}
    for _ in range(repeat):
        for model in times:
            t0 = time.perf_counter()
            quiet(path, "gs", em_model=model, **kw)
            times[model].append(time.perf_counter() - t0)
    g, c = (float(np.median(times[m])) for m in ("gamma", "cascade"))
    print(
        f"gs wall time, median of {repeat}: gamma {g:.2f} s, cascade (default) {c:.2f} s, "
        f"ratio {c / g:.2f}"
    )


def main(data: Path) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if data.is_dir():
            print(f"real ProEM gain series ({data}), authors' φ")
            path = manifest(data.resolve(), tmp)
            profile(path)
            timing(path)
        sim = simulate_gain_series(tmp / "sim", **SIM)
        truth = np.array([a["em_gain"] for a in sim.truth["acquisitions"]][1:])
        print(f"\nsimulated: {SIM}")
        profile(sim.manifest, truth)
        timing(sim.manifest)


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else DATA)
