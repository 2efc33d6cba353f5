"""``emccdcal calibrate MANIFEST -m METHOD -o OUT``: the main job."""

from __future__ import annotations

import sys
from pathlib import Path

from . import _common


def add_parser(subparsers):
    from ..defaults import DEFAULT_BLOCK, DEFAULT_TILE_PIXELS, INTERVALS, METHODS

    p = subparsers.add_parser(
        "calibrate",
        help="calibrate from a manifest (the main job)",
        description="Fit a calibration method to the acquisitions of a manifest and write "
        "OUT/calibration.nc and OUT/summary.json.",
    )
    p.add_argument("manifest", type=Path, help="TOML manifest of the acquisitions")
    p.add_argument(
        "--method",
        "-m",
        default=None,
        choices=METHODS,
        metavar="METHOD",
        help="which data it suits (default: gs, or is-adu where the manifest's "
        "camera_kind has no EM register): gs, a gain series with its 1x "
        "acquisition and phi known -> the gains; gs-no1x, the same without 1x; "
        "gs-hierarchical, gs with per-set-point light; is-adu, a 1x intensity "
        "series -> phi; is-gain, an intensity series at one set-point, phi known "
        "-> its gain; mv-adu, mv-gain, the photon-transfer (mean-variance) "
        "versions of is-adu and gs",
    )
    _common.add_out(p, overwrite=False)
    _common.add_e_per_adu(p)
    again = p.add_mutually_exclusive_group()
    again.add_argument(
        "--resume",
        action="store_true",
        help="continue the interrupted run in OUT (refused if its inputs changed)",
    )
    again.add_argument(
        "--overwrite", action="store_true", help="replace what OUT holds of an earlier run"
    )
    execution = p.add_argument_group("execution")
    execution.add_argument(
        "--tile-pixels",
        type=_common.positive_int,
        default=DEFAULT_TILE_PIXELS,
        help="pixels read, fitted and kept at once; memory grows with it (default %(default)s)",
    )
    execution.add_argument(
        "--block-size",
        type=_common.positive_int,
        default=DEFAULT_BLOCK,
        help="pixels fitted together (default %(default)s)",
    )
    execution.add_argument(
        "--workers",
        type=_common.positive_int,
        default=None,
        help="threads, or local processes (default: the CPUs; 1 per task on a Dask cluster)",
    )
    execution.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="run the tiles on a Dask cluster, e.g. tcp://10.0.0.1:8786 (the "
        "workers read the manifest's paths; needs the 'dask' extra), or "
        "'processes': in --workers local processes, one thread each; 'threads': "
        "here, on --workers threads (default: processes for a sensor of 4096 pixels "
        "or more in two tiles per worker, else threads)",
    )
    _common.add_device(execution)
    p.add_argument(
        "--no-checks",
        action="store_true",
        help="skip the data-quality checks (see 'emccdcal check')",
    )
    p.add_argument(
        "--intervals",
        choices=INTERVALS,
        default="wald",
        help="'profile': also write 95 %% profile-likelihood bounds "
        "(<name>_lower/_upper), for skewed likelihoods; slower (default: wald). "
        "mv-adu and mv-gain always write Fieller bounds, gs-hierarchical those "
        "of its model without the prior",
    )
    prior = p.add_argument_group(
        "gs-hierarchical hyperprior", "the priors of the hierarchical model: docs/methods.md"
    )
    prior.add_argument(
        "--mu-sd",
        type=float,
        metavar="E",
        help="scale of mu's normal prior, e- (default: the authors' 25, for an "
        "illumination of ~370 e-; scale it in proportion to yours)",
    )
    prior.add_argument(
        "--sigma-sd",
        type=float,
        metavar="E",
        help="scale of sigma_E's half-normal prior, e- (default 25; as --mu-sd)",
    )
    prior.add_argument(
        "--prior-centre",
        choices=("gs", "setpoint"),
        help="centre of mu's prior: each pixel's shared-E (gs) estimate (default) "
        "or the authors' (<S> - S0)*phi/set-point",
    )
    p.add_argument(
        "--conditional-se",
        action="store_true",
        help="standard errors conditional on the offset/read-noise maps (leave out "
        "the error of maps estimated from dark frames)",
    )
    p.add_argument(
        "--report",
        action="store_true",
        help="also write OUT/report.html (figures, summary, provenance)",
    )
    _common.add_em_model(p)
    _common.add_quiet(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from .. import result
    from .._output import comment
    from ..calibration import calibrate, format_summary

    options = {
        key: value
        for key, value in (
            ("mu_sd", args.mu_sd),
            ("sigma_sd", args.sigma_sd),
            ("centre", args.prior_centre),
        )
        if value is not None
    }
    with _common.recording_warnings() as caught:
        ds = calibrate(
            args.manifest,
            args.method,
            e_per_adu=args.e_per_adu,
            out=args.out,
            resume=args.resume,
            overwrite=args.overwrite,
            tile_pixels=args.tile_pixels,
            block_size=args.block_size,
            workers=args.workers,
            scheduler=args.scheduler,
            options=options,
            progress=not args.quiet,
            checks=not args.no_checks,
            map_errors=not args.conditional_se,
            intervals=args.intervals,
            em_model=args.em_model,
            stages=args.stages,
            accept_mismatch=args.accept_mismatch,
            accept_phi=args.accept_phi,
            device=args.device,
        )
        if args.report:
            from ..report.html import REPORT_FILE, write_report

            write_report([args.out], args.out / REPORT_FILE, progress=not args.quiet)
    if not args.quiet:
        print(format_summary(ds))
        print(f"wrote {args.out / result.CALIBRATION_FILE} and {args.out / result.SUMMARY_FILE}")
        if args.report:
            print(f"wrote {args.out / REPORT_FILE}")
    _common.print_warnings(caught)
    # the last line: the verdict, after the numbers and findings it is about
    line = comment(result.verdict_line(ds))
    if result.is_doubtful(ds):
        print(f"emccdcal calibrate: {line.removeprefix('verdict: ')}", file=sys.stderr)
        return 1
    if not args.quiet:
        print(line)
    return 0
