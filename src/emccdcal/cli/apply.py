"""``emccdcal apply RESULT MOVIE -o OUT``: a movie's counts to photoelectrons per pixel."""

from __future__ import annotations

from pathlib import Path

from . import _common


def add_parser(subparsers):
    from ..defaults import PHOTON_THRESHOLD as DEFAULT_THRESHOLD

    p = subparsers.add_parser(
        "apply",
        help="convert a movie to photoelectrons per pixel, (S - offset) * phi / g",
        description="Convert a movie's raw counts (ADU) to photoelectrons per pixel per "
        "frame, (S - offset) * e_per_adu / em_gain at the movie's set-point, streaming "
        "(bounded memory); TIFF or Zarr out, units in the metadata.",
    )
    _common.add_calibration_source(p)
    p.add_argument("movie", type=Path, metavar="MOVIE", help="the movie (any supported format)")
    p.add_argument(
        "-o",
        "--out",
        type=Path,
        required=True,
        metavar="OUT",
        help="output .tif/.tiff (BigTIFF) or .zarr",
    )
    p.add_argument(
        "--setpoint",
        type=_common.positive_float,
        metavar="G",
        help="the movie's EM-gain set-point (default: what its file records)",
    )
    p.add_argument(
        "--photon-counting",
        action="store_true",
        help="threshold each pixel-frame into 0/1 photon counts (high gain)",
    )
    p.add_argument(
        "--threshold",
        type=_common.positive_float,
        default=DEFAULT_THRESHOLD,
        metavar="K",
        help="photon-counting threshold in read-noise SDs (default %(default)s)",
    )
    p.add_argument(
        "--qe",
        type=_common.positive_float,
        metavar="Q",
        help="quantum efficiency at the emission wavelength (0 < Q <= 1): "
        "write photons, photoelectrons / Q",
    )
    _common.add_overwrite(p)
    _common.add_quiet(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from ..data.stacks import stack_settings
    from ..export.movie import apply

    setpoint = args.setpoint
    if setpoint is None and (args.camera is not None or args.gain_curve is not None):
        setpoint = stack_settings(args.movie, setpoint_from_name=True).em_gain_setpoint
    with _common.recording_warnings() as caught:
        out = apply(
            _common.calibration_of(args, setpoint),
            args.movie,
            args.out,
            setpoint=args.setpoint,
            photon_counting=args.photon_counting,
            threshold=args.threshold,
            progress=not args.quiet,
            overwrite=args.overwrite,
            accept_mismatch=args.accept_mismatch,
            qe=args.qe,
        )
    if not args.quiet:
        print(f"wrote {out}")
    _common.print_warnings(caught)
    return 0
