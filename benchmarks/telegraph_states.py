"""How many offset states a random-telegraph pixel holds: the count against the truth.

Simulated darks (``CMOSCamera``: 40 × 40 px, a tenth of the pixels random-telegraph with
k = 2, 3 or 4 offset states ``--steps`` read-noise widths apart, switching with
probability 0.05 per frame) go through :func:`emccdcal.data.telegraph.telegraph_pixels`.
Per camera, k and step: the fraction of the RTS pixels whose states are counted k, the
fraction counted more than k, and (per camera) the one-normal pixels counted more than
two (a flagged one-normal pixel is counted two by construction).

With ``--cost``: what the count adds to the test's time instead (100 × 100 px, 3000
frames, 1 % and 10 % three-state pixels four widths apart; medians of three runs
alternating with and without the count, their ratio).

Run: ``.venv/bin/python benchmarks/telegraph_states.py [--seeds 1,2,3] [--frames 3000]``
(about a minute per seed), or ``... --cost`` (half a minute).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from emccdcal.data import telegraph
from emccdcal.data.telegraph import telegraph_pixels
from emccdcal.simulate.cmos import CMOSCamera, simulate_cmos_frames

CAMERAS = (("sCMOS (1.4 e-)", "scmos", None), ("qCMOS (0.27 e-)", "qcmos", None),
           ("quiet sCMOS (0.3 e-)", "scmos", 0.3))  # fmt: skip


def counted(kind, read_noise_e, states, step, seeds, frames):
    """(the RTS pixels' counts (n,), the one-normal pixels' counts (m,)) over ``seeds``."""
    rts, normal = [], []
    quiet = {} if read_noise_e is None else {"read_noise_e": read_noise_e}
    for seed in seeds:
        camera = CMOSCamera(
            kind=kind, rows=40, cols=40, rts_fraction=0.1, rts_step=step, rts_states=states,
            **quiet,
        )  # fmt: skip
        rng = np.random.default_rng(seed)
        maps = camera.maps(rng)
        dark = simulate_cmos_frames(
            0.0, maps, frames, rng, rts_switch=camera.rts_switch, rts_states=states
        )
        found = telegraph_pixels(dark).states
        truth = maps["rts_step"].ravel() > 0
        rts.append(found[truth])
        normal.append(found[~truth])
    return np.concatenate(rts), np.concatenate(normal)


def cost() -> None:
    """The test's time with the count against without it (module docstring)."""
    count = telegraph._count_states
    for fraction in (0.01, 0.1):
        camera = CMOSCamera(rows=100, cols=100, rts_fraction=fraction, rts_states=3)
        rng = np.random.default_rng(3)
        maps = camera.maps(rng)
        dark = simulate_cmos_frames(
            0.0, maps, 3000, rng, rts_switch=camera.rts_switch, rts_states=3
        )
        telegraph_pixels(dark)  # warm: the null table read, the imports done
        times: dict[str, list] = {"with": [], "without": []}
        for _ in range(3):
            for mode in times:
                telegraph._count_states = count if mode == "with" else _two
                t0 = time.perf_counter()
                telegraph_pixels(dark)
                times[mode].append(time.perf_counter() - t0)
        telegraph._count_states = count
        with_, without = (float(np.median(times[m])) for m in ("with", "without"))
        print(
            f"{fraction:.0%} three-state pixels: {with_:.2f} s with the count, "
            f"{without:.2f} s without, ratio {with_ / without:.2f}"
        )


def _two(values, counts, loglik, x):
    """Every flagged pixel two states: the test without the count."""
    return np.full(values.shape[0], 2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1,2,3", help="comma-separated")
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--steps", default="1.5,2,3,4", help="read-noise widths, comma-separated")
    ap.add_argument("--cost", action="store_true", help="the count's time instead")
    args = ap.parse_args()
    if args.cost:
        cost()
        return
    seeds = [int(s) for s in args.seeds.split(",")]
    steps = [float(s) for s in args.steps.split(",")]
    head = ", ".join(f"{s:g}" for s in steps)
    print(f"{args.frames} dark frames, seeds {args.seeds}")
    print(f"| camera | states | counted right at {head} widths | counted more | pixels |")
    print("| --- | --- | --- | --- | --- |")
    for name, kind, read_noise_e in CAMERAS:
        spurious = 0
        for states in (2, 3, 4):
            right, more = [], []
            for step in steps:
                rts, normal = counted(kind, read_noise_e, states, step, seeds, args.frames)
                right.append(np.mean(rts == states))
                more.append(np.mean(rts > states))
                spurious += int(np.sum(normal > 2))
            print(
                f"| {name} | {states} | {', '.join(f'{r:.2f}' for r in right)} "
                f"| {max(more):.3f} | {rts.size} |",
                flush=True,
            )
        print(f"| {name} | one normal counted more than two | {spurious} | | |", flush=True)


if __name__ == "__main__":
    main()
