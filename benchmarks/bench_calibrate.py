"""Benchmark: manifest → written result for paper-size series (the calibration engine).

Simulates (once, into a temporary directory) a 32 × 32 px gain series — set-points
1/5/25/100/300, 5000 frames each — and a six-level 1× intensity series, then times
``emccdcal calibrate`` for ``gs``, ``gs-no1x``, ``is-adu`` (and the other methods) in a
fresh subprocess each, reporting wall time and peak resident memory (with the
data-quality checks, which are on by default, and for ``gs`` also without them).

Run: ``.venv/bin/python benchmarks/bench_calibrate.py [--methods gs,is-adu] [--repeat 3]``

``--cascade`` times every method under the gamma model and under the exact cascade (the
default register model), alternating, and prints the ratio of the medians (cascade/gamma).
``--multiplication cascade`` simulates the gain series with the exact register (default:
the gamma model's, as the paper's simulations): each model needs one Newton iteration
more on the other's data.

``--em-model gamma`` fits every method with the gamma model (default: the package's
default register), on both sides of ``--against``.

``--against SRC`` also times another version of the package (the ``src`` folder of a
checkout, e.g. made by ``git worktree add /tmp/old REV``) on the same data, alternating
the two in every repetition, and prints the ratio of the medians: on a shared, noisy
machine a ratio is only meaningful when both sides were measured in one run.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CHILD = r"""
import resource, sys, time, warnings
warnings.simplefilter("ignore")
t0 = time.perf_counter()
from emccdcal import calibrate
kw = dict(out=sys.argv[3], checks=sys.argv[4] == "checks")
if sys.argv[5] != "default":  # the EM register model
    kw["em_model"] = sys.argv[5]
try:  # versions that refuse to write into an earlier run's directory
    calibrate(sys.argv[1], sys.argv[2], overwrite=True, **kw)
except TypeError:
    calibrate(sys.argv[1], sys.argv[2], **kw)
wall = time.perf_counter() - t0
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(f"{wall:.2f} {peak:.0f}")
"""


def machine():
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import numpy
    import scipy

    return (
        f"{platform.node()}: {os.cpu_count()} cores, {cpu}, Python {platform.python_version()}, "
        f"NumPy {numpy.__version__}, SciPy {scipy.__version__}"
    )


def _time(manifest, method, out, checks, src=None, em_model="default"):
    """Wall time (s) and peak memory (MB) of one calibration in a fresh process."""
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = str(Path(src).resolve())
    res = subprocess.run(
        [
            sys.executable,
            "-c",
            CHILD,
            str(manifest),
            method,
            str(out),
            "checks" if checks else "no-checks",
            em_model,
        ],
        capture_output=True,
        text=True,
        check=True,
        env=env,
    )
    wall, peak = res.stdout.split()
    return float(wall), float(peak)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--methods",
        default="gs,gs:no-checks,gs-no1x,gs-hierarchical,mv-gain,is-adu,mv-adu",
        help="comma-separated; ':no-checks' skips the data-quality checks",
    )
    parser.add_argument("--rows", type=int, default=32)
    parser.add_argument("--frames", type=int, default=5000)
    parser.add_argument("--repeat", type=int, default=1, help="runs per method (median shown)")
    parser.add_argument(
        "--against",
        type=Path,
        default=None,
        help="the src folder of another version to time alternately",
    )
    parser.add_argument(
        "--cascade",
        action="store_true",
        help="time each method under the gamma and the cascade register "
        "model alternately and print the ratio cascade/gamma",
    )
    parser.add_argument(
        "--multiplication",
        choices=("gamma", "cascade"),
        default="gamma",
        help="the register of the simulated gain series",
    )
    parser.add_argument(
        "--em-model",
        choices=("default", "gamma", "cascade"),
        default="default",
        help="the register model of the fits (with --against: of both sides)",
    )
    args = parser.parse_args()
    from emccdcal.simulate.series import simulate_gain_series, simulate_intensity_series

    print(machine())
    print(time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        kw = dict(rows=args.rows, cols=args.rows, frames=args.frames, seed=1)
        gs = simulate_gain_series(tmp / "gs", multiplication=args.multiplication, **kw)
        adu = simulate_intensity_series(tmp / "adu", **kw)
        print(
            f"{args.rows}x{args.rows} px, {args.frames} frames per acquisition, "
            f"{args.multiplication} register in the gain series, median of {args.repeat}"
        )
        head = f"{'method':<18}{'wall s':>8}{'peak MB':>9}"
        if args.against is not None:
            head += f"{'other s':>9}{'other MB':>10}{'ratio':>7}"
        if args.cascade:
            head += f"{'cascade s':>10}{'cascade MB':>11}{'ratio':>7}"
        print(head)
        for entry in args.methods.split(","):
            method, _, flag = entry.partition(":")
            manifest = adu.manifest if method in ("is-adu", "mv-adu") else gs.manifest
            out = tmp / f"out-{method}"
            checks = flag != "no-checks"
            mine, other = [], []
            # with --cascade the first column is the paper's gamma model, named (the
            # default register model is the cascade)
            base = "gamma" if args.cascade else args.em_model
            for _ in range(args.repeat):
                mine.append(_time(manifest, method, out, checks, em_model=base))
                if args.against is not None:
                    other.append(_time(manifest, method, out, checks, args.against, em_model=base))
                if args.cascade:
                    other.append(_time(manifest, method, out, checks, em_model="cascade"))
            wall = statistics.median(w for w, _ in mine)
            line = f"{entry:<18}{wall:>8.2f}{max(p for _, p in mine):>9.0f}"
            if other:
                wall_o = statistics.median(w for w, _ in other)
                ratio = wall_o / wall if args.cascade else wall / wall_o
                line += f"{wall_o:>9.2f}{max(p for _, p in other):>10.0f}{ratio:>7.2f}"
            print(line)


if __name__ == "__main__":
    main()
