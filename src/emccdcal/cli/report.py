"""``emccdcal report RESULT [RESULT ...] -o OUT``: a self-contained HTML report."""

from __future__ import annotations

from pathlib import Path

from . import _common


def add_parser(subparsers):
    p = subparsers.add_parser(
        "report",
        help="write a self-contained HTML report of calibration results",
        description="Write one self-contained HTML file (figures embedded, no network) "
        "with the summary, warnings, goodness of fit, figures and provenance of one or "
        "more calibration results.",
    )
    p.add_argument(
        "results",
        nargs="+",
        type=Path,
        metavar="RESULT",
        help="calibration.nc files or the directories that hold them",
    )
    _common.add_out(
        p, "output directory (the report is OUT/report.html), or the .html file to write"
    )
    p.add_argument(
        "--validation",
        type=Path,
        action="append",
        default=[],
        metavar="DIR",
        help="a bead-validation directory (emccdcal validate -o DIR); repeatable",
    )
    p.add_argument(
        "--pixel",
        type=_common.pixel,
        metavar="ROW,COL",
        help="pixel of the histogram and photon-transfer figures (default: centre)",
    )
    p.add_argument(
        "--figures-dir",
        type=Path,
        metavar="DIR",
        help="also write every figure as PNG and SVG into DIR",
    )
    p.add_argument(
        "--db",
        type=Path,
        metavar="PATH",
        help="a calibration database: show each result's camera history (its "
        "calibrations and gain checks, and what db compare flags)",
    )
    p.add_argument(
        "--camera",
        metavar="SERIAL",
        help="with --db: the camera's serial where the result records none",
    )
    _common.add_quiet(p)
    p.set_defaults(func=run)
    return p


def _command(args) -> str:
    words = ["emccdcal", "report", *map(str, args.results), "-o", str(args.out)]
    words += [w for d in args.validation for w in ("--validation", str(d))]
    if args.pixel is not None:
        words += ["--pixel", f"{args.pixel[0]},{args.pixel[1]}"]
    if args.figures_dir is not None:
        words += ["--figures-dir", str(args.figures_dir)]
    if args.db is not None:
        words += ["--db", str(args.db)]
    if args.camera is not None:
        words += ["--camera", args.camera]
    return " ".join(words)


def run(args) -> int:
    from ..report.html import REPORT_FILE, write_report

    out = args.out if args.out.suffix.lower() in (".html", ".htm") else args.out / REPORT_FILE
    from ..result import result_files

    inputs = result_files(args.results)
    with (
        _common.recording_warnings() as caught,
        _common.output(args, out, kind="file", inputs=inputs),
    ):
        path = write_report(
            args.results,
            out,
            validation=args.validation,
            pixel=args.pixel,
            figures_dir=args.figures_dir,
            progress=not args.quiet,
            command=_command(args),
            db=args.db,
            camera=args.camera,
        )
    if not args.quiet:
        print(f"wrote {path}")
    _common.print_warnings(caught)
    return 0
