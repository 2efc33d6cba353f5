"""Benchmark: simulating a paper-size gain series (emccdcal.simulate, emccdcal.cascade).

Paper size: set-points 1/5/25/100/300 (true gains 1, 4.78, 22.95, 90.06, 261.6),
32×32 px, 5000 frames per set-point, E = 370 e⁻/px/frame. Targets: ≤ 10 s with
gamma multiplication, ≤ 60 s with the exact 536-stage cascade.

Timed:
1. in memory (:func:`emccdcal.simulate.simulate_frames`, the five signal stacks);
2. to disk (:func:`emccdcal.simulate.simulate_gain_series`: five signal stacks, five
   dark stacks of 5000 frames, their maps, truth.json, manifest; uint16 TIFF);
3. the stage-by-stage binomial sampler (``cascade_method="stages"``) on a slice of the
   frames, extrapolated to the paper size (the full run takes minutes; ``--full-stages``
   runs it);
4. whether NumPy's binomial sampler gains from two threads with independent generators.

The pmf tables of the exact sampler are built inside every timed run (cache cleared).

Run: ``.venv/bin/python benchmarks/bench_simulate.py [--full-stages]``. Figures are
written down in ``docs/benchmarks.md`` (section "Simulation").
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import shutil
import sys
import tempfile
import threading
import time

import numpy as np

from emccdcal import __version__
from emccdcal.model import cascade_sampling
from emccdcal.model.cascade_sampling import sample_cascade
from emccdcal.simulate.camera import (
    PAPER_SETPOINTS,
    default_em_gain,
    offset_at_setpoint,
    simulate_frames,
)
from emccdcal.simulate.series import simulate_gain_series

ROWS, COLS, FRAMES, E = 32, 32, 5000, 370.0


def machine() -> dict:
    cpu = "unknown"
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {
        "date": datetime.date.today().isoformat(),
        "cpu": cpu,
        "nproc": affinity,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "emccdcal": __version__,
        "platform": platform.platform(),
    }


def in_memory(
    multiplication: str, method: str = "pmf", frames: int = FRAMES, gains_only=False
) -> float:
    cascade_sampling._TABLES.clear()  # include building the pmf tables
    t0 = time.perf_counter()
    for i, s in enumerate(PAPER_SETPOINTS):
        g = default_em_gain(s)
        if gains_only and g == 1:
            continue
        simulate_frames(
            E,
            g,
            offset=offset_at_setpoint(s),
            frames=frames,
            rows=ROWS,
            cols=COLS,
            multiplication=multiplication,
            cascade_method=method,
            seed=i,
        )
    return time.perf_counter() - t0


def to_disk(multiplication: str) -> tuple[float, int]:
    out = tempfile.mkdtemp(prefix="bench-simulate-")
    cascade_sampling._TABLES.clear()
    try:
        t0 = time.perf_counter()
        res = simulate_gain_series(out, multiplication=multiplication, seed=1)
        dt = time.perf_counter() - t0
        size = sum(p.stat().st_size for p in res.files)
        return dt, size
    finally:
        shutil.rmtree(out, ignore_errors=True)


def cascade_only(method: str, frames: int) -> float:
    """Time of the cascade alone (4 gain set-points) for ``frames`` frames."""
    rng = np.random.default_rng(0)
    n = rng.poisson(E, (frames, ROWS, COLS))
    cascade_sampling._TABLES.clear()
    t0 = time.perf_counter()
    for s in PAPER_SETPOINTS[1:]:
        sample_cascade(n, default_em_gain(s), 536, rng, method=method)
    return time.perf_counter() - t0


def threads_binomial(size: int = 1_000_000, stages: int = 40) -> tuple[float, float]:
    """Stage-by-stage binomial work: one thread vs two threads with spawned generators."""
    n0 = np.random.default_rng(0).poisson(E, size).astype(np.int64)
    p = 261.6 ** (1 / 536) - 1

    def work(gen, x):
        for _ in range(stages):
            x += gen.binomial(x, p)

    a = n0.copy()
    t0 = time.perf_counter()
    work(np.random.default_rng(1), a)
    one = time.perf_counter() - t0
    gens = np.random.SeedSequence(2).spawn(2)
    parts = [n0[: size // 2].copy(), n0[size // 2 :].copy()]
    threads = [
        threading.Thread(target=work, args=(np.random.default_rng(s), x))
        for s, x in zip(gens, parts)
    ]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return one, time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--full-stages", action="store_true", help="run the stage-by-stage sampler at full size"
    )
    ap.add_argument(
        "--stage-frames", type=int, default=100, help="frames of the stage-by-stage slice"
    )
    args = ap.parse_args(argv)

    info = machine()
    print("# emccdcal simulation benchmark")
    for k, v in info.items():
        print(f"{k:>9}: {v}")
    print(
        f"paper size: set-points {PAPER_SETPOINTS}, {ROWS}x{COLS} px, {FRAMES} frames, E = {E:g} e-"
    )
    print()

    simulate_frames(
        E, 4.78, frames=10, rows=ROWS, cols=COLS, multiplication="cascade", seed=0
    )  # warm up

    rows = []
    g_mem = min(in_memory("gamma") for _ in range(2))
    rows.append(("gamma, in memory (5 signal stacks)", g_mem, 10.0))
    c_mem = in_memory("cascade")
    rows.append(("cascade 536 stages (pmf sampler), in memory", c_mem, 60.0))
    g_disk, size = to_disk("gamma")
    rows.append((f"gamma, to disk (+5 darks, maps; {size / 1e6:.0f} MB)", g_disk, 10.0))
    c_disk, _ = to_disk("cascade")
    rows.append(("cascade 536 stages (pmf sampler), to disk", c_disk, 60.0))
    if args.full_stages:
        s_mem = in_memory("cascade", "stages")
        rows.append(("cascade 536 stages (stage-by-stage binomial), in memory", s_mem, 60.0))
    else:
        f = args.stage_frames
        s_part = cascade_only("stages", f)
        p_part = cascade_only("pmf", f)
        s_est = s_part * FRAMES / f + (g_mem - 0.0)  # cascade part + the rest of the pipeline
        print(
            f"stage-by-stage binomial sampler, cascade only, {f} frames x 4 gains: {s_part:.2f} s "
            f"(pmf sampler on the same: {p_part:.2f} s)"
        )
        rows.append(
            (
                f"cascade, stage-by-stage binomial, in memory (extrapolated from {f} frames)",
                s_est,
                60.0,
            )
        )

    print(f"{'task':<75} {'seconds':>8} {'target':>7}")
    for name, sec, target in rows:
        print(f"{name:<75} {sec:>8.2f} {target:>7.0f}")

    one, two = threads_binomial()
    print()
    print(
        f"binomial, 1e6 elements x 40 stages: 1 thread {one:.2f} s, 2 threads (spawned generators) "
        f"{two:.2f} s -> speed-up {one / two:.2f}x"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
