"""Benchmark: the whole sensor. Peak memory and time per pixel of ``gs`` against sensor size.

Simulates a gain series — set-points 1/5/25/100/300, ``--frames`` frames each (uint16
TIFF), dark maps from 50 dark frames — at each size of ``--sizes`` (square sensors),
then runs ``emccdcal calibrate --method gs`` (data-quality checks included) in a fresh
process and reports its wall time, time per pixel and peak resident memory: of the
calling process, and of it with its worker processes together, where the tiles ran in
local processes (calibrate's default on a large sensor; ``--scheduler threads`` or
``processes`` chooses). A streaming engine keeps the peak flat and the time per pixel
constant.

``--dask N[,M...]`` instead times the same calibration of the first size on a local Dask
cluster of N (then M ...) single-threaded worker processes, alternating, and prints the
speed-up over the first.

``--workers 1,2[,...]`` instead times the calibration of the first size with each number
of threads (here, no cluster), alternating, median of 2, and prints each one's speed-up
over the first and its parallel efficiency (speed-up over the ratio of threads); with
``--processes``, of local processes (``scheduler="processes"``) instead.

``--em-models gamma,cascade`` instead times the calibration of every size under each
register model, alternating in one run, and prints each time's ratio to the first
model's (the default register's cost against the paper's gamma model).

Run: ``.venv/bin/python benchmarks/bench_sensor.py [--sizes 64,128,256] [--frames 5000]``
(``--keep DIR`` keeps the simulated data there: 512 x 512 x 5000 x 5 is 13 GB).
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_calibrate import machine

CHILD = r"""
import sys, time, warnings
warnings.simplefilter("ignore")
t0 = time.perf_counter()
from emccdcal import calibrate
scheduler = None  # the default: processes for a large sensor, else threads
if sys.argv[3] in ("processes", "threads"):
    scheduler = sys.argv[3]
elif sys.argv[3] != "local":
    from distributed import Client, LocalCluster
    cluster = LocalCluster(n_workers=int(sys.argv[3]), threads_per_worker=1, processes=True,
                           host="127.0.0.1", dashboard_address=None)
    client = Client(cluster)
    scheduler = client
    t0 = time.perf_counter()
calibrate(sys.argv[1], "gs", out=sys.argv[2], overwrite=True, scheduler=scheduler,
          em_model=sys.argv[4] if sys.argv[4] != "-" else None,
          workers=int(sys.argv[5]) if sys.argv[5] != "-" else None)
wall = time.perf_counter() - t0
print(f"{wall:.2f}")
"""


def _rss_mb(pid):
    """Resident memory of process ``pid`` (MB; 0 once it is gone), from /proc."""
    try:
        with open(f"/proc/{pid}/status") as f:
            return next(int(x.split()[1]) for x in f if x.startswith("VmRSS:")) / 1024
    except (OSError, StopIteration):
        return 0.0


def _children(pid):
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as f:
            return [int(c) for c in f.read().split()]
    except OSError:
        return []


def _time(manifest, out, where="local", em_model="-", workers="-"):
    """Wall time (s) and peak memory (MB) of one calibration in a fresh process: its own
    resident memory, and the largest sum of its and its worker processes', both sampled
    every 0.05 s from /proc. (Not ``ru_maxrss``: a process started by fork and exec
    keeps its parent's high-water mark, so a calibration started from this script after
    it simulated a 2.6 GB stack reported 2.6 GB.)"""
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(manifest), str(out), where, em_model, str(workers)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    own = tree = 0.0
    while proc.poll() is None:
        mine = _rss_mb(proc.pid)
        own = max(own, mine)
        tree = max(tree, mine + sum(_rss_mb(p) for p in _children(proc.pid)))
        time.sleep(0.05)
    stdout, stderr = proc.communicate()
    if proc.returncode != 0:
        raise SystemExit(f"calibrate failed:\n{stderr[-2000:]}")
    return float(stdout.split()[-1]), own, tree


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", default="64,128,256")
    p.add_argument("--frames", type=int, default=5000)
    p.add_argument("--dask", default=None, help="worker counts to compare, e.g. 1,2")
    p.add_argument("--workers", default=None, help="thread counts to compare, e.g. 1,2")
    p.add_argument(
        "--processes",
        action="store_true",
        help="with --workers: local processes (scheduler='processes'), not threads",
    )
    p.add_argument(
        "--em-models", default=None, help="register models to compare, e.g. gamma,cascade"
    )
    p.add_argument("--keep", type=Path, default=None, help="keep the simulated data here")
    p.add_argument(
        "--scheduler",
        default="local",
        choices=("local", "threads", "processes"),
        help="where the tiles run: calibrate's default (local), or threads or processes",
    )
    args = p.parse_args()
    from emccdcal.simulate.series import simulate_gain_series

    print(machine())
    print(time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    base = Path(tempfile.mkdtemp(prefix="emccdcal-sensor-")) if args.keep is None else args.keep
    try:
        sizes = [int(s) for s in args.sizes.split(",")]
        manifests = {}
        for n in sizes:
            folder = base / f"gs-{n}"
            if not (folder / "manifest.toml").is_file():
                t0 = time.perf_counter()
                simulate_gain_series(
                    folder, rows=n, cols=n, frames=args.frames, dark_frames=50, seed=1
                )
                print(f"simulated {n}x{n}: {time.perf_counter() - t0:.0f} s", flush=True)
            manifests[n] = folder / "manifest.toml"
        if args.dask or args.workers:
            # workers of a local Dask cluster, or this machine's threads or processes
            dask = bool(args.dask)
            counts = [int(c) for c in (args.dask if dask else args.workers).split(",")]
            kind = (
                "Dask workers (1 thread each)"
                if dask
                else "local processes"
                if args.processes
                else "threads"
            )
            where = "processes" if args.processes else "threads"
            n = sizes[0]
            times = {c: [] for c in counts}
            for _ in range(2):
                for c in counts:
                    out = base / f"out-{c}"
                    times[c].append(
                        (
                            _time(manifests[n], out, str(c))
                            if dask
                            else _time(manifests[n], out, where, workers=c)
                        )[0]
                    )
            ref = statistics.median(times[counts[0]])
            print(f"gs, {n}x{n} px, {args.frames} frames; {kind}, alternating, median of 2")
            for c in counts:
                t = statistics.median(times[c])
                speedup = ref / t
                print(
                    f"  {c:>2} {kind}: {t:8.1f} s   speed-up {speedup:5.2f}   "
                    f"efficiency {speedup * counts[0] / c:5.2f}"
                )
            return
        if args.em_models:
            models = args.em_models.split(",")
            print(
                f"gs with data-quality checks, {args.frames} frames per set-point; "
                "register models alternating, median of 2"
            )
            for n, manifest in manifests.items():
                times = {m: [] for m in models}
                for _ in range(2):
                    for m in models:
                        times[m].append(_time(manifest, base / f"out-{n}-{m}", em_model=m)[0])
                ref = statistics.median(times[models[0]])
                for m in models:
                    t = statistics.median(times[m])
                    print(f"  {n}x{n} {m:>8}: {t:8.1f} s   ratio {t / ref:5.2f}", flush=True)
            return
        print(f"gs with data-quality checks, {args.frames} frames per set-point")
        print(
            f"{'sensor':>10}{'pixels':>9}{'wall s':>9}{'ms/pixel':>10}{'peak MB':>9}"
            f"{'with workers MB':>17}"
        )
        for n, manifest in manifests.items():
            wall, peak, tree = _time(manifest, base / f"out-{n}", args.scheduler)
            print(
                f"{n:>6}x{n:<3}{n * n:>9}{wall:>9.1f}{1000 * wall / (n * n):>10.2f}{peak:>9.0f}"
                f"{tree:>17.0f}",
                flush=True,
            )
    finally:
        if args.keep is None:
            shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    main()
