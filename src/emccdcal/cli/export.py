"""``emccdcal export RESULT --to TOOL -o OUT``: a calibration in a localization tool's file."""

from __future__ import annotations

from . import _common


def add_parser(subparsers):
    from .. import plugins

    p = subparsers.add_parser(
        "export",
        help="write a calibration in a localization tool's own file",
        description="Write the calibration in the file, names and units of a localization "
        "tool (docs/exports.md): medians over converged pixels, maps where the tool reads "
        "them, provenance in every file. RESULTs of one read-out mode merge; RESULTs of "
        "several modes of one camera (output amplifier, read-out rate, pre-amp gain) make "
        "Picasso's table of modes (its nested Sensitivity).",
    )
    _common.add_calibration_source(p, many=True)
    p.add_argument(
        "--to",
        required=True,
        **_common.plugin_choice(plugins.TOOLS, "tool"),
        help="the tool or format (another package's too, emccdcal.plugins)",
    )
    _common.add_out(p)
    p.add_argument(
        "--setpoint",
        type=_common.positive_float,
        metavar="G",
        help="EM-gain set-point of the movies the tool will read (needed where "
        "the calibration has several)",
    )
    p.add_argument(
        "--qe",
        type=_common.positive_float,
        metavar="QE",
        help="quantum efficiency, photoelectrons per photon (default: tools that "
        "need it get 1, so their photons are photoelectrons)",
    )
    p.add_argument(
        "--pixel-size",
        type=_common.positive_float,
        metavar="NM",
        help="pixel size in the sample plane, nm (written where a tool takes it)",
    )
    p.add_argument(
        "--camera-name", metavar="NAME", help="the camera's name in Picasso's configuration"
    )
    _common.add_quiet(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from ..export.toolkit import readout_mode
    from ..export.tools import export, export_modes
    from ..result import load_calibration

    options = dict(
        setpoint=args.setpoint,
        qe=args.qe,
        pixel_size_nm=args.pixel_size,
        camera_name=args.camera_name,
    )
    with _common.recording_warnings() as caught:
        each = (
            [load_calibration(r) for r in args.results]
            if args.camera is None and len(args.results) > 1
            else []
        )
        if len({readout_mode(c) for c in each}) > 1:  # one calibration per read-out mode
            with _common.output(args, args.out, inputs=[f for c in each for f in c.files]):
                files = export_modes(each, args.to, args.out, **options)
        else:
            cal = _common.calibration_of(args, args.setpoint)
            with _common.output(args, args.out, inputs=cal.files):
                files = export(cal, args.to, args.out, **options)
    if not args.quiet:
        for f in files:
            print(f"wrote {f}")
    _common.print_warnings(caught)
    return 0
