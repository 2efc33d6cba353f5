"""Benchmark: profile-likelihood bounds. Time and constrained refits.

Simulates (once) the known-truth studies' "other" camera (``known_truth.CAMERAS``: 32 × 32
pixels, set-points 1/10/100/1000, a 10× set-point whose own data hardly see E) and
calibrates it with ``gs-hierarchical``, whose intervals are the profile bounds of each
set-point alone wherever the Wald one is unreliable (``layouts.unpooled_bounds``), on one
thread, in a fresh process for each version of the package given (``--against SRC``, the
``src`` folder of another checkout, e.g. made by ``git worktree add /tmp/old REV``; this
checkout's always), alternating, ``--repeat`` times. It prints each version's median wall
time, its constrained refits (calls and pixel-refits) and the largest difference between
the versions' bounds, in units of the interval's own width.

Run: ``.venv/bin/python benchmarks/bench_profile.py [--against /tmp/old/src]``
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from bench_calibrate import machine

CHILD = r"""
import json, sys, time, warnings
sys.path[:0] = [sys.argv[1], sys.argv[4]]
warnings.simplefilter("ignore")
from known_truth import CAMERAS, hierarchical_options
from emccdcal import calibrate
from emccdcal.fit import profile
counts = {"calls": 0, "pixel_refits": 0}
fit = profile.fit
def counted(layout, blocks, start, **kw):
    counts["calls"] += 1
    counts["pixel_refits"] += start.shape[0]
    return fit(layout, blocks, start, **kw)
profile.fit = counted
t0 = time.perf_counter()
ds = calibrate(sys.argv[2], "gs-hierarchical", options=hierarchical_options(CAMERAS["other"]),
               scheduler="threads", workers=1, progress=False)
wall = time.perf_counter() - t0
ds.to_netcdf(sys.argv[3])
print(json.dumps({"wall": wall, **counts}))
"""

HERE = Path(__file__).resolve().parent
SRC = str(HERE.parent / "src")
BOUNDS = ("photoelectrons", "em_gain")


def _run(src, manifest, out):
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, src, str(manifest), str(out), str(HERE)],
        capture_output=True,
        text=True,
    )
    if proc.returncode:
        raise SystemExit(f"calibrate failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.splitlines()[-1])


def _width_difference(a, b):
    """The largest difference of two results' bounds, as a fraction of the interval."""
    import xarray as xr

    with xr.open_dataset(a) as x, xr.open_dataset(b) as y, np.errstate(invalid="ignore"):
        worst = 0.0
        for name in BOUNDS:
            width = np.log(x[f"{name}_upper"].values) - np.log(x[f"{name}_lower"].values)
            for side in ("lower", "upper"):
                d = np.abs(np.log(x[f"{name}_{side}"].values) - np.log(y[f"{name}_{side}"].values))
                worst = max(worst, float(np.nanmax(d / width)))
    return worst


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--against", action="append", default=[], help="another src folder")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    sys.path.insert(0, str(HERE))
    from known_truth import CAMERAS, simulate_camera

    print(machine())
    with tempfile.TemporaryDirectory(prefix="emccdcal-profile-") as tmp:
        base = Path(tmp)
        manifest = simulate_camera(base / "sim", CAMERAS["other"])["gs"]
        versions = {"this checkout": SRC, **{src: src for src in args.against}}
        runs = {v: [] for v in versions}
        for i in range(args.repeat):
            for k, (name, src) in enumerate(versions.items()):
                runs[name].append(_run(src, manifest, base / f"{k}-{i}.nc"))
        for k, (name, rs) in enumerate(runs.items()):
            walls = [r["wall"] for r in rs]
            print(
                f"{name}: median {statistics.median(walls):.2f} s of {len(rs)} "
                f"({', '.join(f'{w:.2f}' for w in walls)}); "
                f"{rs[0]['calls']} refits, {rs[0]['pixel_refits']} pixel-refits"
            )
            if k:
                diff = _width_difference(base / "0-0.nc", base / f"{k}-0.nc")
                print(f"  bounds against this checkout's: at most {diff:.2e} of the interval")


if __name__ == "__main__":
    main()
