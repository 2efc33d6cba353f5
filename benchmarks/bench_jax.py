"""Benchmark: the likelihood through JAX (``--device jax``) against NumPy, on this machine.

Simulates a small gain series (``--size`` square, ``--frames`` frames per set-point,
set-points 1/5/25/100/300) and calibrates it with ``gs`` (no data-quality checks) under
``--em-model``: with NumPy, then twice through JAX in one fresh process (the first call
compiles every operation for every array shape it meets; the second finds them
compiled), alternating with NumPy in fresh processes, median of ``--repeat``. Prints the
three times, their ratios to NumPy's, and the largest relative difference between the
two results over every floating variable (target 1e-9).

Run: ``.venv/bin/python benchmarks/bench_jax.py [--size 8] [--frames 500]
[--em-model gamma] [--repeat 2]`` (needs the ``jax`` extra).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_calibrate import machine

CHILD = r"""
import json, sys, time, warnings
import numpy as np
warnings.simplefilter("ignore")
from emccdcal import calibrate
manifest, em_model, device, out = sys.argv[1:5]
times = []
for _ in range(1 if device == "cpu" else 2):
    t0 = time.perf_counter()
    ds = calibrate(manifest, "gs", checks=False, em_model=em_model, device=device,
                   progress=False, scheduler="threads")
    times.append(time.perf_counter() - t0)
ds.to_netcdf(out)
print(json.dumps(times))
"""


def _run(manifest, em_model, device, out):
    res = subprocess.run(
        [sys.executable, "-c", CHILD, str(manifest), em_model, device, str(out)],
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(res.stdout.strip().splitlines()[-1])


def _largest_difference(a_path, b_path):
    import numpy as np
    import xarray as xr

    with xr.open_dataset(a_path) as a, xr.open_dataset(b_path) as b:
        worst = 0.0
        for name in a.data_vars:
            if a[name].dtype.kind != "f":
                continue
            x, y = a[name].values, b[name].values
            ok = np.isfinite(x) & np.isfinite(y)
            if ok.any():
                rel = np.abs(x[ok] - y[ok]) / np.maximum(np.abs(x[ok]), 1e-300)
                worst = max(worst, float(rel.max()))
        return worst


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=8)
    p.add_argument("--frames", type=int, default=500)
    p.add_argument("--em-model", default="gamma")
    p.add_argument("--repeat", type=int, default=2)
    args = p.parse_args()
    import jax

    from emccdcal.simulate.series import simulate_gain_series

    print(machine(), f"JAX {jax.__version__} on {jax.devices()[0]}")
    print(time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    base = Path(tempfile.mkdtemp(prefix="emccdcal-jax-"))
    n = args.size
    sim = simulate_gain_series(
        base / "gs", rows=n, cols=n, frames=args.frames, seed=1, progress=False
    )
    numpy_s, cold, warm = [], [], []
    for r in range(args.repeat):
        numpy_s += _run(sim.manifest, args.em_model, "cpu", base / "numpy.nc")
        first, second = _run(sim.manifest, args.em_model, "jax", base / "jax.nc")
        cold.append(first)
        warm.append(second)
    ref = statistics.median(numpy_s)
    print(
        f"gs, {n}x{n} px, 5 x {args.frames} frames, {args.em_model} register, no checks, "
        f"one thread; fresh processes, alternating, median of {args.repeat}"
    )
    for label, times in (
        ("NumPy", numpy_s),
        ("JAX, first call", cold),
        ("JAX, second call", warm),
    ):
        t = statistics.median(times)
        print(f"  {label:<17} {t:8.2f} s   {t / ref:7.1f} x NumPy")
    diff = _largest_difference(base / "numpy.nc", base / "jax.nc")
    print(f"  largest relative difference, JAX against NumPy: {diff:.2e}")


if __name__ == "__main__":
    main()
