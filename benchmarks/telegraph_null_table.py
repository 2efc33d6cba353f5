"""Write the random-telegraph test's table of null quantiles.

``emccdcal.data.telegraph`` flags a pixel whose likelihood ratio (two offset states
against one) exceeds the ratio's 99 % quantile for normal darks of the same frames and
read noise. That quantile is simulated once here, on 20 000 one-normal pixels per cell
(each cell seeded by its place in the table, so any cell can be recomputed alone:
``tests/test_cmos.py`` recomputes one), and written to
``src/emccdcal/data/_telegraph_null.py``; the test interpolates it in log frames. Other
frames, false-alarm rates or seeds are simulated when asked, as before.

Usage::

    python benchmarks/telegraph_null_table.py [--workers 2]

About 10 minutes of one core (2026-11-30).
"""

from __future__ import annotations

import argparse
import datetime
import subprocess
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from emccdcal.data import _telegraph_null as table
from emccdcal.data.telegraph import _NULL_SIGMAS, _null_quantile

#: Frames of the table's rows: 100 to 50 000, about 1.5 apart.
FRAMES = (100, 150, 200, 300, 500, 700, 1000, 1500, 2000, 3000, 5000, 7000, 10000, 15000,
          20000, 30000, 50000)  # fmt: skip
OUT = Path(__file__).resolve().parents[1] / "src" / "emccdcal" / "data" / "_telegraph_null.py"


def cell(i: int, j: int) -> float:
    """The quantile at FRAMES[i] frames and _NULL_SIGMAS[j] ADU, seeded by (i, j)."""
    rng = np.random.default_rng([table.SEED, i, j])
    return _null_quantile(FRAMES[i], _NULL_SIGMAS[j], table.FALSE_ALARM, rng, table.PIXELS)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    places = [(i, j) for i in range(len(FRAMES)) for j in range(len(_NULL_SIGMAS))]
    with ProcessPoolExecutor(args.workers) as pool:
        values = dict(zip(places, pool.map(cell, *zip(*places))))
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=OUT.parent
    ).stdout.strip()
    rows = "\n".join(
        "    (" + ", ".join(repr(values[i, j]) for j in range(len(_NULL_SIGMAS))) + "),"
        for i in range(len(FRAMES))
    )
    OUT.write_text(
        f'''"""The random-telegraph test's null quantiles (written by
benchmarks/telegraph_null_table.py on {datetime.date.today()} at {commit}; do not edit).

QUANTILES[i][j]: the (1 − FALSE_ALARM) quantile of twice the log-likelihood ratio of two
offset states to one (``emccdcal.data.telegraph``) over PIXELS one-normal pixels of
FRAMES[i] rounded normal counts of read noise SIGMAS[j] (ADU), offsets uniform within a
count; the cell's draws seeded by ``numpy.random.default_rng([SEED, i, j])``.
"""

FALSE_ALARM = {table.FALSE_ALARM!r}
PIXELS = {table.PIXELS!r}
SEED = {table.SEED!r}
# fmt: off
FRAMES = {FRAMES!r}
SIGMAS = {tuple(_NULL_SIGMAS)!r}
QUANTILES = (
{rows}
)
# fmt: on
''',
        encoding="utf-8",
    )
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
