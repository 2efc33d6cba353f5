"""Benchmark: the likelihood on a GPU against the same machine's CPU cores, in one run.

Simulates a gain series (set-points 1/5/25/100/300, ``--frames`` frames each, uint16
TIFF, dark maps from 50 frames) at each size of ``--sizes``, then calibrates it with
``gs`` (data-quality checks on) under each register model of ``--em-models`` (the
default register and the paper's gamma model), on ``--device`` (default ``cuda``) and on
the CPU, each in a fresh process, one after the other, and prints for each: the wall
time end to end (read, histograms, fit, result), the fit's share (the time spent in the
tiles' fits, where they ran in the calling process: on the CPU a large sensor's tiles
run in local processes, calibrate's default, and show "-"), the ratio CPU/device, and
the largest relative difference between the two results over every estimate, standard
error and goodness-of-fit p-value (target 1e-9). ``--device jax`` runs JAX's first
device (its GPU where it has one) instead of CuPy's.

Run where a GPU is: ``python benchmarks/bench_gpu.py [--sizes 256,512] [--frames 5000]``.
Without one, ``--device array-api-strict --sizes 16 --frames 200`` runs the same path
on the CPU (a check of the script and of the array API path, no speed figure).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench_calibrate import machine

CHILD = r"""
import json, sys, time, warnings
warnings.simplefilter("ignore")
t0 = time.perf_counter()
from emccdcal import calibrate, calibration
manifest, out, em_model, device = sys.argv[1:5]
fit = [0.0]
fit_pixels = calibration.tiles._fit_pixels
def timed(*args, **kwargs):  # the tiles' fits (one tile at a time here)
    t = time.perf_counter()
    try:
        return fit_pixels(*args, **kwargs)
    finally:
        fit[0] += time.perf_counter() - t
calibration.tiles._fit_pixels = timed
ds = calibrate(manifest, "gs", out=out, overwrite=True, em_model=em_model, device=device,
               progress=False)
# on the CPU a large sensor's tiles run in local processes (calibrate's default, the
# cores' best): their fits are not timed here
print(json.dumps({"wall": time.perf_counter() - t0, "fit": fit[0] or None,
                  "device": ds.attrs["device"]}))
"""

#: What is compared between the two results: every estimate, its SE and the GOF p-value.
COMPARED = ("photoelectrons", "photoelectrons_se", "em_gain", "em_gain_se", "gof_pvalue")


def _run(manifest, out, em_model, device):
    res = subprocess.run(
        [sys.executable, "-c", CHILD, str(manifest), str(out), em_model, device],
        capture_output=True,
        text=True,
    )
    if res.returncode != 0:
        raise SystemExit(f"calibrate on {device} failed:\n{res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def _largest_difference(a_dir, b_dir):
    """Largest relative difference of the compared variables (where both are finite), and
    whether the two results converged at the same pixels."""
    from emccdcal import load_result

    a, b = load_result(a_dir), load_result(b_dir)
    same = bool(np.array_equal(a.converged.values, b.converged.values))
    worst = 0.0
    for name in COMPARED:
        x, y = a[name].values, b[name].values
        ok = np.isfinite(x) & np.isfinite(y)
        if ok.any():
            rel = np.abs(x[ok] - y[ok]) / np.maximum(np.abs(x[ok]), 1e-300)
            worst = max(worst, float(rel.max()))
    return worst, same


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", default="256")
    p.add_argument("--frames", type=int, default=5000)
    p.add_argument("--em-models", default="cascade,gamma")
    p.add_argument("--device", default="cuda")
    p.add_argument("--keep", type=Path, default=None, help="keep the simulated data here")
    args = p.parse_args()
    from emccdcal.simulate.series import simulate_gain_series

    print(machine())
    print(time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    _describe_device(args.device)
    base = Path(tempfile.mkdtemp(prefix="emccdcal-gpu-")) if args.keep is None else args.keep
    try:
        print(f"gs, data-quality checks on, {args.frames} frames per set-point, fresh processes")
        print(
            f"{'sensor':>9} {'model':>8} {'cpu s':>8} {'(fit)':>7} "
            f"{args.device + ' s':>12} {'(fit)':>7} {'ratio':>7} {'max rel diff':>13} "
            f"{'same pixels':>12}"
        )
        for n in (int(s) for s in args.sizes.split(",")):
            folder = base / f"gs-{n}"
            if not (folder / "manifest.toml").is_file():
                t0 = time.perf_counter()
                simulate_gain_series(
                    folder, rows=n, cols=n, frames=args.frames, dark_frames=50, seed=1
                )
                print(f"  (simulated {n}x{n}: {time.perf_counter() - t0:.0f} s)", flush=True)
            manifest = folder / "manifest.toml"
            for model in args.em_models.split(","):
                cpu_out, dev_out = base / f"cpu-{n}-{model}", base / f"dev-{n}-{model}"
                cpu = _run(manifest, cpu_out, model, "cpu")
                dev = _run(manifest, dev_out, model, args.device)
                worst, same = _largest_difference(cpu_out, dev_out)
                share = lambda run: "-" if run["fit"] is None else f"{run['fit']:.1f}"  # noqa: E731
                print(
                    f"{n:>5}x{n:<3} {model:>8} {cpu['wall']:8.1f} {share(cpu):>7} "
                    f"{dev['wall']:12.1f} {share(dev):>7} {cpu['wall'] / dev['wall']:7.2f} "
                    f"{worst:13.2e} {str(same):>12}",
                    flush=True,
                )
    finally:
        if args.keep is None:
            shutil.rmtree(base, ignore_errors=True)


def _describe_device(device):
    """The card (or namespace) the device runs on, as its library names it."""
    from emccdcal import _xp

    xp, dev = _xp.resolve(device)
    name = str(dev)
    if device == "cuda":
        try:
            import cupy

            name = cupy.cuda.runtime.getDeviceProperties(dev.id)["name"].decode()
        except Exception:  # noqa: BLE001 - PyTorch's device instead
            import torch

            name = torch.cuda.get_device_name(dev)
    print(f"device: {device} ({xp.__name__}, {name})")


if __name__ == "__main__":
    main()
