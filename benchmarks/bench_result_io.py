"""Benchmark: what a result file's checksum costs to write and to check.

A full-sensor result (512 × 512 px, 5 set-points: φ, gains, offsets, read noise, E, their
SEs) is saved with :func:`emccdcal.result.save` (the NetCDF file copied behind its
checksum block, and ``summary.json``) and, in the same run, with a plain ``to_netcdf``;
then read with :func:`emccdcal.result.load` (checksum and domain rules checked) and with a
plain ``xarray.open_dataset(...).load()``. Each is timed as the best of ``--repeat`` runs and
the ratios printed (docs/benchmarks.md).

Run: ``.venv/bin/python benchmarks/bench_result_io.py [--size 512] [--repeat 5]``
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import xarray as xr

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_calibrate import machine  # noqa: E402 - one description of the machine

from emccdcal import result  # noqa: E402


def _result(size: int):
    rng = np.random.default_rng(0)
    sps = [1.0, 5.0, 25.0, 100.0, 300.0]
    shape = (size, size)
    g = np.stack(
        [np.ones(shape) if s == 1 else s * (0.9 + 0.01 * rng.standard_normal(shape)) for s in sps]
    )
    return result.make_dataset(
        method="gs",
        setpoints=sps,
        e_per_adu=3.8 + 0.01 * rng.standard_normal(shape),
        e_per_adu_se=0.01,
        em_gain=g,
        em_gain_se=np.where(g == 1, 0.0, 0.002 * g),
        photoelectrons=np.full(shape, 370.0),
        photoelectrons_se=1.0,
        converged=True,
        manifest_hash="0" * 64,
        extra={
            "offset": (("setpoint", "row", "col"), np.full((5, *shape), 600.0), "ADU"),
            "read_noise": (("setpoint", "row", "col"), np.full((5, *shape), 15.0), "ADU"),
        },
    )


def _best(fn, repeat):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    ds = _result(args.size)
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        plain = d / "plain.nc"
        t_plain = _best(lambda: ds.to_netcdf(plain, engine="h5netcdf"), args.repeat)
        t_save = _best(lambda: result.save(ds, d / "res"), args.repeat)
        size_mb = (d / "res" / result.CALIBRATION_FILE).stat().st_size / 1e6

        def read_plain():
            with xr.open_dataset(plain, engine="h5netcdf") as f:
                f.load()

        t_read = _best(read_plain, args.repeat)
        t_load = _best(lambda: result.load(d / "res"), args.repeat)
    print(f"machine: {machine()}")
    print(f"result: {args.size} x {args.size} px, 5 set-points, {size_mb:.0f} MB")
    print(
        f"write: plain to_netcdf {t_plain:.2f} s, result.save (checksum block, summary) "
        f"{t_save:.2f} s, ratio {t_save / t_plain:.2f}"
    )
    print(
        f"read: plain open_dataset {t_read:.2f} s, result.load (checksum, domain checked) "
        f"{t_load:.2f} s, ratio {t_load / t_read:.2f}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
