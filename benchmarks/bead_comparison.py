"""The paper's comparison of methods by bead validation, on data from an exact EM register.

Simulates, on one 64 × 64 px sensor (φ = 3.859 e⁻/ADU, read noise 15.5 ADU, the paper's
true gains 4.78 / 22.95 / 90.06 / 261.6 at 5 / 25 / 100 / 300×), with the *exact*
536-stage Bernoulli cascade (excess-noise factor 1.79 at 5×, not the gamma model's 2):

* a 1× intensity series (six levels, 2000–64000 e⁻) for ``is-adu`` and ``mv-adu``;
* an intensity series at each of 5 / 25 / 100 / 300× (six levels, factor 2 apart, the
  brightest at about 30 000 ADU) for ``is-gain`` and ``mv-gain``, one result per set-point,
  with φ from ``is-adu`` (``mv-adu`` for ``mv-gain``);
* a gain series (1 / 5 / 25 / 100 / 300×, E = 370 e⁻) for ``gs``, ``gs-no1x`` and
  ``gs-hierarchical``, with φ from ``is-adu``;
* bead movies (10 beads, 5000 e⁻ per frame, 500 frames per set-point) for the
  validation, and ``cots`` (calibration-on-the-spot on the beads themselves).

Then ``emccdcal.validation.validate`` fits the beads under every calibration (and the
truth) and ranks them by the spread of the per-set-point mean intensities. Prints the
table, writes ``docs/figures/beads/`` (figures and ``bead_comparison.json``).

``--halo F`` gives the bead movies a PSF that the Gaussian does not describe (a fraction F
of each bead's light in a halo of 3× the width); ``--psf gaussian residual`` validates
with each spot model in turn (the residual image is the paper's second pass), to show
whether it changes the ranking. Outputs are suffixed ``_cascade``, ``_halo<F>`` and
``_<psf>`` where those differ from the defaults.

Run: ``.venv/bin/python benchmarks/bead_comparison.py [--work DIR] [--frames 5000]``.
Long (tens of minutes); every stage is skipped when its output exists in ``--work``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
import warnings
from pathlib import Path

import numpy as np
from bench_calibrate import (
    machine,  # one description of the machine for every benchmark
)

REPO = Path(__file__).resolve().parents[1]
FIGURES = REPO / "docs" / "figures" / "beads"
GAIN_SETPOINTS = (5, 25, 100, 300)
TRUE_GAIN = {1: 1.0, 5: 4.78, 25: 22.95, 100: 90.06, 300: 261.6}
PHI = 3.859


def log(msg):
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def simulate(work, args):
    from emccdcal.simulate.beads import simulate_beads
    from emccdcal.simulate.series import simulate_gain_series, simulate_intensity_series

    common = dict(rows=args.rows, cols=args.cols, multiplication="cascade", seed=None)
    jobs = [
        (
            "adu",
            lambda d, s: simulate_intensity_series(
                d, setpoint=1, frames=args.frames, **(common | {"seed": s})
            ),
        )
    ]
    for sp in GAIN_SETPOINTS:
        # brightest level near 30 000 ADU above offset, six levels a factor 2 apart
        top = 30000.0 * PHI / TRUE_GAIN[sp]
        levels = [top / 2**k for k in range(5, -1, -1)]
        jobs.append(
            (
                f"is-{sp}x",
                lambda d, s, sp=sp, levels=levels: simulate_intensity_series(
                    d, setpoint=sp, levels=levels, frames=args.frames, **(common | {"seed": s})
                ),
            )
        )
    jobs.append(
        ("gs", lambda d, s: simulate_gain_series(d, frames=args.frames, **(common | {"seed": s})))
    )
    jobs.append(
        (
            _beads_dir(args),
            lambda d, s: simulate_beads(
                d,
                frames=args.bead_frames,
                beads=args.beads,
                halo=args.halo,
                **(common | {"seed": s}),
            ),
        )
    )
    for i, (name, run) in enumerate(jobs):
        d = work / name
        if (d / "manifest.toml").is_file():
            continue
        t0 = time.perf_counter()
        run(d, args.seed + i)
        log(f"simulated {name} in {time.perf_counter() - t0:.0f} s")


def _beads_dir(args):
    return "beads" if args.halo == 0 else f"beads-halo{args.halo:g}"


def calibrate_all(work, em_model="gamma", beads="beads"):
    """Every method's calibration; the likelihood methods and mv-gain's F² under the
    register model ``em_model`` (is-adu and mv-adu have none to choose)."""
    from emccdcal import calibrate, result

    def run(name, manifest, method, phi=None):
        model = None if method in ("is-adu", "mv-adu") else em_model
        out = work / ("cal" if em_model == "gamma" or model is None else f"cal-{em_model}") / name
        if not (out / result.CALIBRATION_FILE).is_file():
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                calibrate(manifest, method, e_per_adu=phi, out=out, checks=False, em_model=model)
            log(f"calibrated {name} in {time.perf_counter() - t0:.0f} s")
        return out / result.CALIBRATION_FILE

    files = {}
    files["is-adu"] = run("is-adu", work / "adu" / "manifest.toml", "is-adu")
    files["mv-adu"] = run("mv-adu", work / "adu" / "manifest.toml", "mv-adu")
    phi_is = result.load(files["is-adu"])["e_per_adu"].values
    phi_mv = result.load(files["mv-adu"])["e_per_adu"].values
    for sp in GAIN_SETPOINTS:
        m = work / f"is-{sp}x" / "manifest.toml"
        files[f"is-gain-{sp}x"] = run(f"is-gain-{sp}x", m, "is-gain", phi_is)
        files[f"mv-gain-{sp}x"] = run(f"mv-gain-{sp}x", m, "mv-gain", phi_mv)
    for method in ("gs", "gs-no1x", "gs-hierarchical"):
        files[method] = run(method, work / "gs" / "manifest.toml", method, phi_is)
    from emccdcal.beads.cots_calibration import cots_calibrate

    # COTS reads the gain through the register's F² like the others (per bead movie: it
    # calibrates on the beads themselves)
    name = "cots" if beads == "beads" else f"cots-{beads}"
    out = work / ("cal" if em_model == "gamma" else f"cal-{em_model}") / name
    if not (out / result.CALIBRATION_FILE).is_file():
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cots_calibrate(work / beads / "manifest.toml", out=out, em_model=em_model)
        log(f"calibrated cots in {time.perf_counter() - t0:.0f} s")
    files["cots"] = out / result.CALIBRATION_FILE
    return files


def gain_table(files):
    """Median over the beads' pixels of each calibration's gain per set-point, and φ."""
    from emccdcal import result

    rows = {}
    for label, spec in files.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cal = result.load_calibration(spec)
        rows[label] = {
            "e_per_adu": float(np.nanmedian(cal.e_per_adu)),
            **{
                str(s): float(np.nanmedian(cal.em_gain[float(s)]))
                for s in GAIN_SETPOINTS
                if float(s) in cal.em_gain
            },
        }
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=Path("/tmp/emccdcal-bead-comparison"))
    parser.add_argument("--rows", type=int, default=64)
    parser.add_argument("--cols", type=int, default=64)
    parser.add_argument("--frames", type=int, default=5000, help="frames per calibration stack")
    parser.add_argument("--bead-frames", type=int, default=500)
    parser.add_argument("--beads", type=int, default=10)
    parser.add_argument("--seed", type=int, default=2021)
    parser.add_argument(
        "--em-model",
        choices=("gamma", "cascade"),
        default="gamma",
        help="register model of the methods' likelihoods and of the bead "
        "fits (the data are always the exact cascade)",
    )
    parser.add_argument(
        "--halo",
        type=float,
        default=0.0,
        help="fraction of the beads' light in a halo (3x the PSF width)",
    )
    parser.add_argument(
        "--psf",
        nargs="+",
        choices=("gaussian", "residual", "residual-pooled"),
        default=["gaussian"],
        help="spot models to validate with, in turn",
    )
    args = parser.parse_args()
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    log(f"machine: {machine()}; work directory {work}")
    t_start = time.perf_counter()
    simulate(work, args)
    beads = _beads_dir(args)
    files = calibrate_all(work, args.em_model, beads)
    for psf in args.psf:
        suffix = (
            ("" if args.em_model == "gamma" else f"_{args.em_model}")
            + ("" if args.halo == 0 else f"_halo{args.halo:g}")
            + ("" if psf == "gaussian" else f"_{psf}")
        )
        compare(work, args, files, beads, psf, suffix, t_start)


def compare(work, args, files, beads, psf, suffix, t_start):
    """Validate every calibration with the spot model ``psf``; table, figures, summary."""
    from emccdcal.beads import validation

    specs = {
        "truth": str(work / beads / "truth_calibration.nc"),
        "mv-adu + mv-gain": ",".join(
            str(files[k]) for k in ["mv-adu"] + [f"mv-gain-{s}x" for s in GAIN_SETPOINTS]
        ),
        "is-adu + is-gain": ",".join(
            str(files[k]) for k in ["is-adu"] + [f"is-gain-{s}x" for s in GAIN_SETPOINTS]
        ),
        "gs": str(files["gs"]),
        "gs-no1x": str(files["gs-no1x"]),
        "gs-hierarchical": str(files["gs-hierarchical"]),
    }
    specs["cots"] = str(files["cots"])
    out = work / f"validation{suffix}"
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        doc = validation.validate(
            work / beads / "manifest.toml", list(specs.values()), out=out, progress=True, psf=psf
        )
    t_validate = time.perf_counter() - t0
    log(f"validated {len(specs)} calibrations in {t_validate:.0f} s")
    from emccdcal.report.figures import write_validation_figures

    write_validation_figures(out, beads=1)
    for w in dict.fromkeys(str(c.message) for c in caught):
        log(f"warning: {w}")
    names = {v: k for k, v in specs.items()}
    print(validation.format_table(doc).replace(str(work) + "/", ""))
    gains = gain_table(specs)

    # Per set-point: mean over beads of (mean intensity / 1× mean) for each calibration.
    summary = {
        "machine": machine(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "seconds_validate": t_validate,
        "seconds_total": time.perf_counter() - t_start,
        "options": vars(args) | {"work": str(work)},
        "calibrations": [],
    }
    for c in doc["calibrations"]:
        rel = {}
        for s in doc["setpoints"]:
            r = [
                b["mean_intensity"][s] / b["mean_intensity"]["1"]
                for b in c["beads"]
                if b["mean_intensity"][s] is not None and b["mean_intensity"]["1"]
            ]
            rel[s] = {"mean": float(np.mean(r)), "sd": float(np.std(r, ddof=1))}
        summary["calibrations"].append(
            {
                "name": names[c["file"]],
                "method": c["method"],
                "sigma_means_incl_1x": c["sigma_means_incl_1x"],
                "sigma_means_excl_1x": c["sigma_means_excl_1x"],
                "sigma_means_incl_1x_ddof1": c["sigma_means_incl_1x_ddof1"],
                "sigma_means_excl_1x_ddof1": c["sigma_means_excl_1x_ddof1"],
                "intensity_relative_to_1x": rel,
                "median_gain": gains[names[c["file"]]],
                "mean_intensity_over_beads": {
                    s: float(np.mean([b["mean_intensity"][s] for b in c["beads"]]))
                    for s in doc["setpoints"]
                },
            }
        )
    summary["ranking"] = [names[f] for f in doc["ranking"]]
    summary["beads"] = len(doc["calibrations"][0]["beads"])
    FIGURES.mkdir(parents=True, exist_ok=True)
    summary["em_model"] = args.em_model
    summary["psf"] = psf
    summary["psf_mismatch"] = doc["calibrations"][0]["psf_mismatch"]
    (FIGURES / f"bead_comparison{suffix}.json").write_text(json.dumps(summary, indent=2) + "\n")
    for name in ("bead_consistency", "bead_intensities_0"):
        shutil.copy(out / f"{name}.png", FIGURES / f"{name}{suffix}.png")
    plot_relative(summary, FIGURES / f"bead_comparison_relative{suffix}.png")
    print("\nmean over beads of (mean intensity at set-point / 1x mean), and median gains:")
    for c in summary["calibrations"]:
        rel = "  ".join(f"{s}x {v['mean']:.4f}" for s, v in c["intensity_relative_to_1x"].items())
        g = "  ".join(f"{k} {v:.4g}" for k, v in c["median_gain"].items())
        print(f"  {c['name']:<18} {rel}\n  {'':<18} {g}")
    log(f"total {time.perf_counter() - t_start:.0f} s; figures and summary in {FIGURES}")


def plot_relative(summary, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    n = len(summary["calibrations"])
    for i, c in enumerate(summary["calibrations"]):
        sps = [float(s) for s in c["intensity_relative_to_1x"]]
        m = [v["mean"] for v in c["intensity_relative_to_1x"].values()]
        sd = [v["sd"] for v in c["intensity_relative_to_1x"].values()]
        dodge = 1 + 0.04 * (i - (n - 1) / 2)
        ax.errorbar(
            np.array(sps) * dodge, m, yerr=sd, fmt="o-", ms=4, capsize=3, label=f"{c['name']}"
        )
    ax.axhline(1.0, color="k", ls=":", lw=1)
    ax.set_xscale("log")
    ax.set_xlabel("EM gain set-point (dimensionless)")
    ax.set_ylabel("bead mean intensity / 1× mean (dimensionless)")
    ax.set_title(f"mean over {summary['beads']} beads ± SD over beads", fontsize=9)
    ax.legend(fontsize=7)
    pos = np.arange(n)
    incl = [100 * c["sigma_means_incl_1x"] for c in summary["calibrations"]]
    excl = [100 * c["sigma_means_excl_1x"] for c in summary["calibrations"]]
    ax2.bar(pos - 0.2, incl, width=0.4, label="with 1×")
    ax2.bar(pos + 0.2, excl, width=0.4, label="without 1×")
    ax2.set_xticks(
        pos, [c["name"] for c in summary["calibrations"]], rotation=30, ha="right", fontsize=8
    )
    ax2.set_ylabel("σ of per-set-point means / 1× mean (%, ddof 0)")
    ax2.set_yscale("log")
    ax2.set_title("consistency metric, mean over beads (lower is better)", fontsize=9)
    ax2.legend(fontsize=8)
    fig.suptitle("Bead validation on exact-cascade data (536 stages)", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
