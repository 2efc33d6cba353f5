"""``emccdcal validate BEAD_MANIFEST -c RESULT ... -o OUT``: the bead validation."""

from __future__ import annotations

from pathlib import Path

from . import _common


def add_parser(subparsers):
    from ..defaults import BEAD_HALF_SIZE as DEFAULT_HALF_SIZE, PSF_WIDTH as DEFAULT_WIDTH

    p = subparsers.add_parser(
        "validate",
        help="bead validation: fit beads under each calibration, compare set-points",
        description="Fit every bead in every frame of a bead manifest under each calibration "
        "(exact noise model) and measure how consistent the beads' intensities are across "
        "gain set-points (Ryan et al. 2021, Figs. 4-5). Writes OUT/validation.json, "
        "OUT/intensities.nc and figures (docs/beads.md).",
    )
    p.add_argument(
        "manifest",
        type=Path,
        metavar="BEAD_MANIFEST",
        help="TOML manifest of the bead stacks (one or more per set-point, 1x included)",
    )
    p.add_argument(
        "--calibration",
        "-c",
        action="append",
        nargs="+",
        required=True,
        metavar="FILE[,FILE...]",
        help="a calibration result (calibration.nc or its directory), or a "
        "comma-joined group merged into one (phi from is-adu/mv-adu, gains from "
        "is-gain results); repeatable",
    )
    _common.add_accept_mismatch(p)
    _common.add_out(p)
    p.add_argument(
        "--width",
        type=_common.positive_float,
        default=DEFAULT_WIDTH,
        help="expected PSF standard deviation, px (default %(default)s)",
    )
    p.add_argument(
        "--half-size",
        type=int,
        default=DEFAULT_HALF_SIZE,
        help="fitting box half-width, px: boxes are (2N+1)^2 (default %(default)s)",
    )
    p.add_argument(
        "--min-separation",
        type=float,
        default=None,
        help="least distance between beads, px (default 2*half-size+1)",
    )
    p.add_argument(
        "--snr",
        type=float,
        default=8.0,
        help="detection threshold, robust noise SDs (default %(default)s)",
    )
    p.add_argument(
        "--detect-setpoint",
        type=float,
        default=None,
        help="set-point whose mean image the beads are found on (default: highest)",
    )
    p.add_argument(
        "--bleaching",
        choices=("correct", "warn"),
        default="correct",
        help="a trend of the beads' intensity within the acquisitions (bleaching): "
        "undo it before comparing set-points, or only warn (default %(default)s)",
    )
    p.add_argument(
        "--psf",
        choices=("gaussian", "residual", "residual-pooled"),
        default="gaussian",
        help="spot model: the Gaussian, or the paper's second pass with each bead's "
        "oversampled residual image added (or one pooled over the beads) "
        "(default %(default)s)",
    )
    p.add_argument(
        "--psf-split",
        choices=("alternate", "time"),
        default="alternate",
        help="with a residual image: build it on one half of the frames and score "
        "it on the other, even/odd frames or first/second half in time "
        "(default %(default)s)",
    )
    p.add_argument(
        "--blinking",
        choices=("model", "ignore"),
        default="model",
        help="beads off in some frames: take the 'on' level of a two-level "
        "mixture where found, or ignore it (default %(default)s)",
    )
    _common.add_no_figures(p)
    _common.add_quiet(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from ..beads.validation import (
        INTENSITIES_FILE,
        VALIDATION_FILE,
        format_table,
        validate,
    )
    from ..errors import OptionError
    from ..result import result_files

    if args.half_size < 2:
        raise OptionError("--half-size must be at least 2 (pixels)")
    specs = [item for group in args.calibration for item in group]
    inputs = [args.manifest, *result_files(specs)]
    with _common.recording_warnings() as caught:
        with _common.output(
            args, args.out, inputs=inputs, names=(VALIDATION_FILE, INTENSITIES_FILE)
        ):
            doc = validate(
                args.manifest,
                specs,
                out=args.out,
                width=args.width,
                half_size=args.half_size,
                min_separation=args.min_separation,
                snr=args.snr,
                detect_setpoint=args.detect_setpoint,
                progress=not args.quiet,
                bleaching=args.bleaching,
                psf=args.psf,
                blinking=args.blinking,
                psf_split=args.psf_split,
                accept_mismatch=args.accept_mismatch,
            )
        if not args.no_figures:  # drawn from the files just published
            from ..report.figures import write_validation_figures

            with _common.output(args, args.out, inputs=inputs):
                write_validation_figures(args.out)
    if not args.quiet:
        print(format_table(doc))
        print(f"wrote {args.out / VALIDATION_FILE} and {args.out / INTENSITIES_FILE}")
    _common.print_warnings(caught)
    return 0
