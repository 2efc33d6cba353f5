"""Is the residual image's goodness of fit honest? Held-out χ² per pixel over seeds.

For ``--seeds`` seeds, beads are simulated (``emccdcal simulate beads``: 64 × 64 px,
10 beads of 5000 e⁻, ``--frames`` frames at 1 / 5 / 25 / 100 / 300×, the paper's gamma
register, fitted with it) and fitted as ``emccdcal validate --psf residual`` does under
the true calibration: each set-point with the width free, again with each bead's width
pooled, then with each bead's residual image added (the offset maps' own error, from
the darks, in the SEs as validate has it). Per set-point, the residual model's χ² per
pixel is scored four ways:

- ``in-sample``: the image built on all frames and scored on them (what validate did
  before: it flatters the image, whose own noise it fits);
- ``held out, image exact``: built on the even frames, scored on the odd, the image
  taken as exact (reads about 1 + 1/set-points: the image's noise is a difference);
- ``held out``: the same with the image's sampling variance counted (what validate
  reports now);
- and, with ``--halo``, the PSF gains a halo (20 % of the light, SD 3.9 px) halfway
  through every acquisition: the image built on the first half (``--psf-split time``)
  is scored on the second, and the even/odd split for comparison.

Printed: per set-point the mean over seeds of each χ² per pixel, with the SD over seeds
and the sampling SE a right model gives (``chi2_per_pixel_se``). docs/beads.md holds the
measured table.

Run: ``.venv/bin/python benchmarks/residual_holdout_study.py [--seeds 8] [--halo]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from emccdcal.beads import fit as bead_fit
from emccdcal.data.manifest import read_manifest
from emccdcal.model.noise import EMModel
from emccdcal.simulate.beads import simulate_beads

GAINS = {1.0: 1.0, 5.0: 4.78, 25.0: 22.95, 100.0: 90.06, 300.0: 261.6}
PHI = 3.859


def fit_series(stacks, manifest, positions, split, image_half):
    """The three passes of validate on one bead series; returns the third pass's fits and
    the image. ``stacks`` maps set-point -> frames; ``image_half`` None (all frames) or 0."""
    acqs = {a.em_gain_setpoint: a for a in manifest.acquisitions}
    model = EMModel("gamma")

    def fit(sp, **kw):
        a = acqs[sp]
        return bead_fit.fit_beads(
            stacks[sp],
            positions,
            offset=a.offset,
            read_noise=a.read_noise,
            e_per_adu=PHI,
            em_gain=GAINS[sp],
            em_model=model,
            residual_split=split,
            offset_se=a.read_noise / np.sqrt(a.dark_frames),
            **kw,
        )

    first = {sp: fit(sp) for sp in stacks}
    widths, widths_se = bead_fit.shared_widths(list(first.values()), with_se=True)
    second = {sp: fit(sp, fixed_width=widths, fixed_width_se=widths_se) for sp in stacks}
    image = bead_fit.residual_image(list(second.values()), half=image_half)
    third = {
        sp: fit(sp, fixed_width=widths, fixed_width_se=widths_se, residual=image) for sp in stacks
    }
    return third, image


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--frames", type=int, default=500)
    ap.add_argument(
        "--halo",
        action="store_true",
        help="also the halo that appears halfway through every acquisition",
    )
    args = ap.parse_args()
    scores: dict = {}
    t0 = time.perf_counter()

    def add(name, sp, m):
        scores.setdefault(name, {}).setdefault(sp, []).append(
            (m["chi2_per_pixel"], m["chi2_per_pixel_se"])
        )

    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            sim = simulate_beads(
                Path(tmp) / f"g{seed}", seed=seed, frames=args.frames, multiplication="gamma"
            )
            manifest = read_manifest(sim.manifest)
            positions = np.array([[round(b["row"]), round(b["col"])] for b in sim.truth["beads"]])
            stacks = {a.em_gain_setpoint: a.frames() for a in manifest.acquisitions}
            third, image = fit_series(stacks, manifest, positions, "alternate", None)
            for sp, f in third.items():
                add("in-sample", sp, bead_fit.psf_mismatch(f))
            third, image = fit_series(stacks, manifest, positions, "alternate", 0)
            for sp, f in third.items():
                add("held out, image exact", sp, bead_fit.psf_mismatch(f, half=1))
                add("held out", sp, bead_fit.psf_mismatch(f, half=1, image=image))
            if args.halo:
                later = simulate_beads(
                    Path(tmp) / f"h{seed}",
                    seed=seed,  # the same camera
                    frames=args.frames,
                    multiplication="gamma",
                    positions=[[b["row"], b["col"]] for b in sim.truth["beads"]],
                    halo=0.2,
                )
                half = args.frames // 2
                mixed = {
                    a.em_gain_setpoint: np.concatenate(
                        [stacks[a.em_gain_setpoint][:half], a.frames()[half:]]
                    )
                    for a in read_manifest(later.manifest).acquisitions
                }
                for split in ("time", "alternate"):
                    third, image = fit_series(mixed, manifest, positions, split, 0)
                    for sp, f in third.items():
                        add(
                            f"halo from mid-way, split {split}",
                            sp,
                            bead_fit.psf_mismatch(f, half=1, image=image),
                        )
            print(f"seed {seed} done ({time.perf_counter() - t0:.0f} s)", flush=True)
    print(
        f"\n{args.seeds} seeds x 10 beads of 5000 e-, {args.frames} frames per set-point; "
        "residual model's chi2 per pixel: mean over seeds (SD over seeds; sampling SE "
        "of one seed's value under a right model)"
    )
    sps = sorted(next(iter(scores.values())))
    print(f"{'score':>36} | " + " | ".join(f"{sp:>17g}x" for sp in sps))
    for name, per in scores.items():
        cells = []
        for sp in sps:
            v = np.array(per[sp])
            cells.append(f"{v[:, 0].mean():.3f} ({v[:, 0].std(ddof=1):.3f}; {v[:, 1].mean():.3f})")
        print(f"{name:>36} | " + " | ".join(f"{c:>18}" for c in cells))


if __name__ == "__main__":
    main()
