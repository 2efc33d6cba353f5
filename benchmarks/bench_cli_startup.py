"""Start-up time of the command line: ``emccdcal --help`` and ``--version`` in fresh processes.

Each command runs ``--repeat`` times in a new interpreter (alternating, so load on this
shared machine hits both alike); the median wall time is printed, with the heavy
libraries the command imported (none of numpy, scipy, xarray, matplotlib should be).

    python benchmarks/bench_cli_startup.py [--repeat 11]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

HEAVY = ("numpy", "scipy", "xarray", "matplotlib", "tifffile", "pandas", "emcee", "statsmodels")
PROBE = (
    "import sys; from emccdcal.cli import main; code = main({argv!r}); "
    "print(sorted({{m.split('.')[0] for m in sys.modules}} & set({heavy!r})), "
    "file=sys.stderr)"
)


def _run(argv):
    t0 = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-c", PROBE.format(argv=argv, heavy=HEAVY)],
        capture_output=True,
        text=True,
        check=True,
    )
    return time.perf_counter() - t0, out.stderr.strip().splitlines()[-1]


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=11)
    args = p.parse_args()
    commands = {
        "--help": ["--help"],
        "--version": ["--version"],
        "calibrate --help": ["calibrate", "--help"],
    }
    times = {k: [] for k in commands}
    heavy = {}
    for _ in range(args.repeat):
        for name, argv in commands.items():
            seconds, imported = _run(argv)
            times[name].append(seconds)
            heavy[name] = imported
    baseline = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", "pass"], check=True)
        baseline.append(time.perf_counter() - t0)
    print(f"python {sys.version.split()[0]}, median of {args.repeat} fresh processes")
    print(f"  {'bare interpreter':<20} {statistics.median(baseline):6.3f} s")
    for name in commands:
        print(
            f"  emccdcal {name:<11} {statistics.median(times[name]):6.3f} s   "
            f"heavy imports: {heavy[name]}"
        )


if __name__ == "__main__":
    main()
