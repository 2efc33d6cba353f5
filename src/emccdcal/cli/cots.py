"""``emccdcal cots BEAD_MANIFEST -o OUT``: calibration-on-the-spot from bead movies."""

from __future__ import annotations

from pathlib import Path

from . import _common


def add_parser(subparsers):
    from ..defaults import BEAD_HALF_SIZE as DEFAULT_HALF_SIZE, PSF_WIDTH as DEFAULT_WIDTH

    p = subparsers.add_parser(
        "cots",
        help="calibration-on-the-spot: EM gain and offset from bead frames",
        description="Calibration-on-the-spot (Mortensen & Flyvbjerg 2016): the gain in ADU "
        "per photoelectron and the offset of every bead at every EM set-point, from the "
        "frame-to-frame variance of its pixels, read through the register's excess-noise "
        "factor (the exact cascade's by default; --em-model gamma: F^2 = 2, COTS as "
        "published); the EM gain is G * e_per_adu (the manifest must give e_per_adu). Writes OUT/calibration.nc and OUT/summary.json.",
    )
    p.add_argument(
        "manifest", type=Path, metavar="BEAD_MANIFEST", help="TOML manifest of the bead stacks"
    )
    _common.add_out(p)
    p.add_argument(
        "--half-size",
        type=_common.positive_int,
        default=DEFAULT_HALF_SIZE,
        help="ROI half-width, px: (2N+1)^2 pixels per bead (default %(default)s)",
    )
    p.add_argument(
        "--width",
        type=_common.positive_float,
        default=DEFAULT_WIDTH,
        help="expected PSF standard deviation, px (default %(default)s)",
    )
    _common.add_em_model(p, auto=False)
    _common.add_quiet(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from .. import result
    from ..beads.cots_calibration import cots_calibrate, format_summary

    names = (result.CALIBRATION_FILE, result.SUMMARY_FILE)
    with (
        _common.recording_warnings() as caught,
        _common.output(args, args.out, inputs=[args.manifest], names=names),
    ):
        ds = cots_calibrate(
            args.manifest,
            half_size=args.half_size,
            width=args.width,
            em_model=args.em_model,
            stages=args.stages,
            progress=not args.quiet,
            out=args.out,
        )
    if not args.quiet:
        print(format_summary(ds))
        print(f"wrote {args.out / result.CALIBRATION_FILE} and {args.out / result.SUMMARY_FILE}")
    _common.print_warnings(caught)
    return 0
