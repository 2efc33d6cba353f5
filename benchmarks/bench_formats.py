"""Benchmark: reading large camera files by row bands keeps memory bounded.

Writes a 2 GB SPE 3.0 file (with LightField's per-frame metadata, so frames lie a
stride apart) and a 2 GB OME-TIFF (512 × 512 px, uint16, 4000 frames each), then, in a
fresh process per file, reads every band of ``--rows`` rows of every frame with
``emccdcal.data.stacks.read_band`` (as a calibration's tiles do) and reports the wall
time and the process's peak resident memory. A read of the whole file would need 2 GB.

Run: ``.venv/bin/python benchmarks/bench_formats.py [--frames 4000] [--rows 2] [--keep DIR]``
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from camera_files import write_spe  # noqa: E402 - the tests' writer of the published layout

CHILD = r"""
import sys, time
from emccdcal.data.stacks import read_band, stack_header
path, rows = sys.argv[1], int(sys.argv[2])
t0 = time.perf_counter()
(n, h, w), _ = stack_header(path)
total = 0
for r0 in range(0, h, rows):
    total += int(read_band(path, r0, r0 + rows)[-1, 0, 0])  # touch the band
wall = time.perf_counter() - t0
# VmHWM: this process's own peak (ru_maxrss can carry the parent's over fork and exec)
hwm = [l for l in open("/proc/self/status") if l.startswith("VmHWM")][0].split()[1]
print(f"{wall:.1f} {int(hwm) / 1024:.0f}")
"""


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=4000)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--rows", type=int, default=2, help="rows per band (a 1024-px tile)")
    parser.add_argument("--keep", type=Path, default=None)
    args = parser.parse_args()
    import tifffile

    print(time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        rng = np.random.default_rng(0)
        frames = rng.integers(500, 4000, (args.frames, args.size, args.size)).astype(np.uint16)
        spe, tif = folder / "big.spe", folder / "big.ome.tif"
        t0 = time.perf_counter()
        write_spe(spe, frames, em_gain=300)
        tifffile.imwrite(tif, frames, ome=True, photometric="minisblack")
        del frames
        print(
            f"wrote {spe.stat().st_size / 1e9:.2f} GB SPE and {tif.stat().st_size / 1e9:.2f} GB "
            f"OME-TIFF in {time.perf_counter() - t0:.0f} s"
        )
        print(f"{'file':<12}{'rows/band':>10}{'wall s':>8}{'peak MB':>9}")
        for path in (spe, tif):
            res = subprocess.run(
                [sys.executable, "-c", CHILD, str(path), str(args.rows)],
                capture_output=True,
                text=True,
                check=True,
            )
            wall, peak = res.stdout.split()
            print(f"{path.suffix:<12}{args.rows:>10}{wall:>8}{peak:>9}")


if __name__ == "__main__":
    main()
