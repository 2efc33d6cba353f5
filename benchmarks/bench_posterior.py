"""Benchmark and validation of ``emccdcal.posterior`` on the real ProEM data.

1. One gain-series pixel (``gain-GS``, method ``gs``, φ from ``ADU_map.tif``): wall time
   of :func:`emccdcal.sample_posterior` (target ≤ 60 s), end to end (reading the
   pixel, maximum-likelihood start, sampling until converged).
2. The ``is-adu`` posterior of φ at every pixel of the ADU series (or ``--pixels``)
   against the engine's estimate and standard error (``calibrate(..., "is-adu")``).

Writes into ``--out`` (default ``/tmp/emccdcal-bench-posterior``): the posterior files of
both runs (``gs/``, ``is-adu/``, with corner plots), ``posterior_vs_se.png`` and
``bench_posterior.json``; prints a Markdown table for ``docs/posterior.md``.

Usage::

    python benchmarks/bench_posterior.py [--out DIR] [--pixels diagonal|all] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
import warnings
from pathlib import Path

import numpy as np

import emccdcal
from emccdcal import calibrate
from emccdcal.fit import posterior

REAL = Path(os.environ.get("EMCCDCAL_PROEM", "/work/shared/data/lanl-proem"))


def _manifest(out, kind):
    lines = []
    if kind == "gs":
        lines.append(f'e_per_adu = "{REAL}/gain-GS/ADU_map.tif"')
        for g in (1, 5, 25, 100, 300):
            lines += [
                "[[acquisition]]",
                f'frames = "{REAL}/gain-GS/{g}x-gain.tif"',
                f"em_gain_setpoint = {g}",
                f'offset = "{REAL}/gain-GS/{g}x-gain_no-signal_S0.tif"',
                f'read_noise = "{REAL}/gain-GS/{g}x-gain_no-signal_sigma.tif"',
            ]
    else:
        for level in range(1, 7):
            lines += [
                "[[acquisition]]",
                f'frames = "{REAL}/ADU/1x-gain_level-0{level}.tif"',
                "em_gain_setpoint = 1",
                f'level = "L{level}"',
                f'offset = "{REAL}/ADU/1x-gain_no-signal_S0.tif"',
                f'read_noise = "{REAL}/ADU/1x-gain_no-signal_sigma.tif"',
            ]
    path = out / f"{kind}.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def _cpu():
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("/tmp/emccdcal-bench-posterior"))
    ap.add_argument("--pixels", choices=("diagonal", "all"), default="all")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if not REAL.is_dir():
        raise SystemExit(f"ProEM data not found at {REAL} (set EMCCDCAL_PROEM)")
    args.out.mkdir(parents=True, exist_ok=True)
    warnings.simplefilter("ignore")  # the manifest's read-noise growth warning
    report = {"machine": f"{os.cpu_count()} cores, {_cpu()}", "seed": args.seed}

    # 1. One gain-series pixel, timed end to end.
    gs = _manifest(args.out, "gs")
    t = time.perf_counter()
    ds = emccdcal.sample_posterior(gs, "gs", [(1, 1)], seed=args.seed)
    seconds = time.perf_counter() - t
    posterior.save(ds, args.out / "gs")
    print(posterior.format_summary(ds))
    report["gs_pixel_1_1"] = {"seconds": seconds, **posterior.summary(ds)["pixels"][0]}
    print(f"gs pixel (1, 1): {seconds:.1f} s (target <= 60 s)\n")

    # 2. is-adu: φ posterior against the engine at every (or every diagonal) pixel.
    adu = _manifest(args.out, "adu")
    engine = calibrate(adu, "is-adu")
    rows, cols = engine.e_per_adu.shape
    pixels = (
        [(i, i) for i in range(min(rows, cols))]
        if args.pixels == "diagonal"
        else [(r, c) for r in range(rows) for c in range(cols)]
    )
    t = time.perf_counter()
    ds = emccdcal.sample_posterior(adu, "is-adu", pixels, seed=args.seed)
    report["is_adu_seconds"] = time.perf_counter() - t
    posterior.save(ds, args.out / "is-adu")
    table = []
    for i, (r, c) in enumerate(pixels):
        phi = ds.sel(parameter="e_per_adu").isel(pixel=i)
        est, se = float(engine.e_per_adu[r, c]), float(engine.e_per_adu_se[r, c])
        table.append(
            {
                "row": r,
                "col": c,
                "engine": est,
                "engine_se": se,
                "median": float(phi["median"]),
                "sd": float(phi.sd),
                "q025": float(phi.q025),
                "q975": float(phi.q975),
                "median_rel": float(phi["median"]) / est - 1,
                "sd_over_se": float(phi.sd) / se,
                "ess": float(phi.ess),
                "tau": float(phi.autocorr_time),
                "acceptance": float(ds.acceptance[i]),
                "seconds": float(ds.seconds[i]),
                "steps": int(ds.n_steps[i]),
            }
        )
    report["is_adu"] = table
    print(
        "| pixel | engine φ ± SE (e⁻/ADU) | posterior median ± SD | 95 % interval | "
        "median/engine − 1 | SD/SE | ESS | τ (steps) | acceptance | steps | time (s) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for t_ in table:
        print(
            f"| ({t_['row']}, {t_['col']}) | {t_['engine']:.4f} ± {t_['engine_se']:.4f} | "
            f"{t_['median']:.4f} ± {t_['sd']:.4f} | [{t_['q025']:.4f}, {t_['q975']:.4f}] | "
            f"{100 * t_['median_rel']:+.3f} % | {t_['sd_over_se']:.3f} | {t_['ess']:.0f} | "
            f"{t_['tau']:.1f} | {t_['acceptance']:.2f} | {t_['steps']} | {t_['seconds']:.1f} |"
        )
    ratios = np.array([t_["sd_over_se"] for t_ in table])
    print(
        f"\nSD/SE: mean {ratios.mean():.3f}, range {ratios.min():.3f}–{ratios.max():.3f}; "
        f"is-adu total {report['is_adu_seconds']:.1f} s for {len(pixels)} pixels"
    )
    _figure(table, args.out / "posterior_vs_se.png")
    (args.out / "bench_posterior.json").write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out}")


def _figure(table, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.6))
    x = np.arange(len(table))
    labels = [f"({t['row']},{t['col']})" for t in table]
    a.errorbar(
        x - 0.1,
        [t["engine"] for t in table],
        [1.96 * t["engine_se"] for t in table],
        fmt="o",
        color="C3",
        label="engine MLE ± 1.96 SE",
    )
    a.errorbar(
        x + 0.1,
        [t["median"] for t in table],
        [[t["median"] - t["q025"] for t in table], [t["q975"] - t["median"] for t in table]],
        fmt="s",
        color="C0",
        label="posterior median, 95 % interval",
    )
    a.set_xticks(x, labels, fontsize=7)
    a.set_ylabel("e_per_adu φ (e⁻/ADU)")
    a.legend(fontsize=7)
    b.plot(x, [t["sd_over_se"] for t in table], "o", color="k")
    b.axhline(1, color="0.5", lw=0.8)
    b.axhspan(0.85, 1.15, color="C2", alpha=0.15, label="±15 %")
    b.set_xticks(x, labels, fontsize=7)
    b.set_ylabel("posterior SD / engine SE")
    b.legend(fontsize=7)
    fig.suptitle(
        "is-adu, real ProEM ADU series: MCMC against observed-information errors", fontsize=9
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
