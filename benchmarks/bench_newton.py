"""Benchmark: the engine's steps. Time, trial evaluations and distance from the optimum.

Simulates (once) a gain series of ``--size`` × ``--size`` pixels at set-points
1/5/25/100/300, ``--frames`` frames each, and calibrates it with ``gs`` on one thread
(``scheduler="threads", workers=1``) in a fresh process for each version of the package
given (``--against SRC``, the ``src`` folder of another checkout, e.g. made by ``git
worktree add /tmp/old REV``; this checkout's always), alternating, ``--repeat`` times.
It prints each version's median wall time, its trial evaluations per pixel (the result's
``iterations``), and how far its estimates (E, g and their SEs, every set-point) lie
from the optimum: the largest relative difference from this checkout's fit with the
stopping tolerance at 1e-13 nats instead of 1e-7 (run once).

Run: ``.venv/bin/python benchmarks/bench_newton.py [--against /tmp/old/src] [--size 32]``
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_calibrate import machine

CHILD = r"""
import sys, time, warnings
sys.path.insert(0, sys.argv[1])
warnings.simplefilter("ignore")
import numpy as np
t0 = time.perf_counter()
from emccdcal import calibrate
if sys.argv[4] == "tight":
    from emccdcal.fit import engine
    fit = engine.fit
    engine.fit = lambda *a, **k: fit(*a, **{**k, "tol": 1e-13, "max_iter": 500})
ds = calibrate(sys.argv[2], "gs", scheduler="threads", workers=1)
wall = time.perf_counter() - t0
np.savez(sys.argv[3], **{k: ds[k].values for k in
    ("photoelectrons", "photoelectrons_se", "em_gain", "em_gain_se", "iterations")})
print(wall)
"""

HERE = str(Path(__file__).resolve().parents[1] / "src")
KEYS = ("photoelectrons", "photoelectrons_se", "em_gain", "em_gain_se")


def _run(src, manifest, out, mode="-"):
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, src, str(manifest), str(out), mode],
        capture_output=True,
        text=True,
    )
    if proc.returncode:
        raise SystemExit(f"calibrate failed:\n{proc.stderr[-2000:]}")
    return float(proc.stdout.split()[-1])


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=32)
    p.add_argument("--frames", type=int, default=5000)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--against", action="append", default=[], help="another version's src")
    args = p.parse_args()
    from emccdcal.simulate.series import simulate_gain_series

    print(machine())
    print(time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    with tempfile.TemporaryDirectory(prefix="emccdcal-newton-") as tmp:
        base = Path(tmp)
        n = args.size
        sim = simulate_gain_series(
            base / "gs", rows=n, cols=n, frames=args.frames, dark_frames=50, seed=1
        )
        _run(HERE, sim.manifest, base / "tight.npz", "tight")
        tight = np.load(base / "tight.npz")
        versions = {"this checkout": HERE, **{src: src for src in args.against}}
        times = {v: [] for v in versions}
        results = {}
        for _ in range(args.repeat):
            for i, (name, src) in enumerate(versions.items()):
                times[name].append(_run(src, sim.manifest, base / f"{i}.npz"))
                results[name] = np.load(base / f"{i}.npz")
        print(
            f"gs, {n}x{n} px x 5 set-points x {args.frames} frames, one thread, "
            f"median of {args.repeat} (alternating)"
        )
        for name in versions:
            res = results[name]
            with np.errstate(invalid="ignore"):  # 0/0: the SEs of fixed gains (1x)
                far = max(float(np.nanmax(np.abs(res[k] / tight[k] - 1.0))) for k in KEYS)
            print(
                f"  {name}: {statistics.median(times[name]):7.2f} s   "
                f"trials per pixel {float(np.mean(res['iterations'])):5.2f}   "
                f"largest relative distance from the optimum {far:.1e}"
            )


if __name__ == "__main__":
    main()
