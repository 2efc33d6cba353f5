"""Benchmark: ``emccdcal apply`` converts a 2 GB movie in bounded memory.

Writes a 2 GB TIFF movie (512 × 512 px, uint16, 4000 frames, written in blocks) and a
512 × 512 calibration, then, in a fresh process each, (a) reads the whole movie block by
block, (b) imports emccdcal and loads the calibration, and (c) runs ``emccdcal apply`` to a
float32 BigTIFF (4.2 GB, flushed to disk before it is renamed into place) and to Zarr;
each reports its wall time and its peak resident memory (VmHWM). What (c) needs beyond
(b) is the streaming's own memory: blocks of 16 MB, whatever the movie's length.

Run: ``.venv/bin/python benchmarks/bench_apply.py [--frames 4000] [--keep DIR]``
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_calibrate import machine  # noqa: E402 - one description of the machine

READ = r"""
import sys, time
from emccdcal.data.stacks import read_band, stack_header
path = sys.argv[1]
t0 = time.perf_counter()
(n, h, w), _ = stack_header(path)
for a in range(0, n, 128):
    read_band(path, 0, h, skip_frames=a, stop_frame=a + 128)
hwm = [l for l in open("/proc/self/status") if l.startswith("VmHWM")][0].split()[1]
print(f"{time.perf_counter() - t0:.1f} {int(hwm) / 1024:.0f}")
"""

CAL = r"""
import sys
from emccdcal.export import movie
from emccdcal.result import load_calibration
load_calibration(sys.argv[1])
hwm = [l for l in open("/proc/self/status") if l.startswith("VmHWM")][0].split()[1]
print(f"0 {int(hwm) / 1024:.0f}")
"""

APPLY = r"""
import sys, time
from emccdcal.export.movie import apply
cal, movie, out = sys.argv[1:4]
t0 = time.perf_counter()
apply(cal, movie, out, setpoint=100, progress=False)
hwm = [l for l in open("/proc/self/status") if l.startswith("VmHWM")][0].split()[1]
print(f"{time.perf_counter() - t0:.1f} {int(hwm) / 1024:.0f}")
"""


def _run(code, *args):
    out = subprocess.run(
        [sys.executable, "-c", code, *map(str, args)], check=True, capture_output=True, text=True
    ).stdout.split()
    return float(out[0]), float(out[1])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=4000)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--keep", type=Path, default=None)
    args = parser.parse_args()
    import tifffile

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_export import true_result

    print(time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "|", machine())
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        movie = folder / "movie.tif"
        shape = (args.frames, args.size, args.size)
        rng = np.random.default_rng(0)

        def blocks():
            for a in range(0, args.frames, 100):
                yield from rng.integers(
                    90, 4000, (min(100, args.frames - a), *shape[1:]), dtype=np.uint16
                )

        tifffile.imwrite(movie, blocks(), shape=shape, dtype=np.uint16, bigtiff=True)
        cal = true_result(folder / "cal", shape=shape[1:])
        size_gb = movie.stat().st_size / 1e9
        print(f"movie: {shape[0]} frames of {shape[1]}×{shape[2]} uint16, {size_gb:.2f} GB")
        t_read, m_read = _run(READ, movie)
        print(f"read only:          {t_read:6.1f} s, peak RSS {m_read:5.0f} MB")
        _, m_cal = _run(CAL, cal)
        print(f"imports + calibration loaded:  peak RSS {m_cal:5.0f} MB")
        for suffix in (".tif", ".zarr"):
            t, m = _run(APPLY, cal, movie, folder / f"electrons{suffix}")
            print(
                f"apply -> {suffix:<6}     {t:6.1f} s, peak RSS {m:5.0f} MB "
                f"({m - m_cal:+.0f} MB over the calibration loaded)"
            )


if __name__ == "__main__":
    main()
