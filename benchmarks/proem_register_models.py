"""The real ProEM gain series under both EM register models, side by side.

Calibrates the gain series of Ryan et al. (2021) (``../shared/data/lanl-proem``, 3 × 3
pixels, set-points 1/5/25/100/300, 5000 frames each, the authors' φ = 3.859 e⁻/ADU and
dark maps) with ``gs`` under the paper's gamma model and under the exact cascade of 536
stages, and prints per set-point: the median gain over the pixels, the summed
log-likelihood, and the goodness of fit (pixels at p < 0.01 and the median p-value), for
docs/cascade.md.

Run: ``.venv/bin/python benchmarks/proem_register_models.py [DATA_DIR]``
"""

from __future__ import annotations

import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

from emccdcal import calibrate

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "lanl-proem"
SETPOINTS = (1, 5, 25, 100, 300)


def manifest(data: Path, directory: Path) -> Path:
    """The gain series' manifest: its stacks, dark maps and the authors' φ map."""
    lines = [f'e_per_adu = "{data}/gain-GS/ADU_map.tif"']
    for g in SETPOINTS:
        lines += [
            "[[acquisition]]",
            f'frames = "{data}/gain-GS/{g}x-gain.tif"',
            f"em_gain_setpoint = {g}",
            f'offset = "{data}/gain-GS/{g}x-gain_no-signal_S0.tif"',
            f'read_noise = "{data}/gain-GS/{g}x-gain_no-signal_sigma.tif"',
        ]
    path = directory / "gs.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def main(data: Path) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = manifest(data.resolve(), Path(tmp))
        results = {}
        for model in ("gamma", "cascade"):
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                results[model] = calibrate(
                    path, "gs", em_model=model, stages=536 if model == "cascade" else None
                )
            misfits = [str(w.message).split(";")[0] for w in caught if "misfit" in str(w.message)]
            print(
                f"{model}: E = {np.median(results[model].photoelectrons.values):.3f} e- "
                f"(median); misfit warnings: {misfits or 'none'}"
            )
    print(
        f"{'set-point':>9} | {'g gamma':>9} {'g cascade':>9} {'ratio':>7} | "
        f"{'loglik gamma':>13} {'loglik cascade':>14} {'Δ':>7} | "
        f"{'p<0.01 gamma':>12} {'cascade':>7} | {'median p gamma':>14} {'cascade':>7}"
    )
    gam, cas = results["gamma"], results["cascade"]
    for i, sp in enumerate(gam.setpoint.values):
        g0, g1 = (float(np.median(r.em_gain.values[i])) for r in (gam, cas))
        ll0, ll1 = (float(r.acquisition_loglik.values[i].sum()) for r in (gam, cas))
        p0, p1 = (r.gof_pvalue.values[i].ravel() for r in (gam, cas))
        print(
            f"{sp:>8g}x | {g0:>9.4f} {g1:>9.4f} {g1 / g0:>7.4f} | {ll0:>13.2f} {ll1:>14.2f} "
            f"{ll1 - ll0:>7.2f} | {int((p0 < 0.01).sum()):>10d}/9 {int((p1 < 0.01).sum()):>5d}/9 | "
            f"{np.median(p0):>14.2g} {np.median(p1):>7.2g}"
        )
    print(
        f"total log-likelihood: gamma {float(gam.loglik.values.sum()):.2f}, "
        f"cascade {float(cas.loglik.values.sum()):.2f}"
    )


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else DATA)
