"""``emccdcal audit TOOLFILE --calibration RESULT|--camera SERIAL``: is a tool right?"""

from __future__ import annotations

from pathlib import Path

from . import _common


def add_parser(subparsers):
    from .. import plugins
    from ..defaults import AUDIT_TOLERANCE as DEFAULT_TOLERANCE

    p = subparsers.add_parser(
        "audit",
        help="check a localization tool's camera settings against a calibration",
        description="Read a localization tool's camera settings (Picasso config.yaml, "
        "ThunderSTORM Camera setup macro, DECODE yaml, gdsc-smlm calibration JSON, SMAP "
        "JSON or cameras.mat, PYME JSON or .md, storm-analysis XML), compare each number "
        "with a calibration in the tool's own words, and say by how much the tool's photon "
        "counts are biased. Exit status 1 where the photons are off by more than the "
        "tolerance or the baseline by more than the offset's spread over pixels plus "
        "1 ADU (docs/exports.md).",
    )
    p.add_argument("toolfile", type=Path, metavar="TOOLFILE", help="the tool's settings file")
    _common.add_calibration_source(p, option=True)
    p.add_argument(
        "--setpoint",
        type=_common.positive_float,
        metavar="G",
        help="EM-gain set-point of the tool's movies (needed where the calibration has several)",
    )
    p.add_argument(
        "--tool",
        **_common.plugin_choice(plugins.TOOLS, "tool"),
        help="the tool (default: recognised from the file)",
    )
    p.add_argument(
        "--tool-gain",
        type=_common.positive_float,
        metavar="G",
        help="the EM gain typed into the tool where its file holds none "
        "(Picasso; default the set-point)",
    )
    p.add_argument(
        "--qe",
        type=_common.positive_float,
        metavar="Q",
        help="the quantum efficiency at the emission wavelength, to check the tool's against",
    )
    p.add_argument(
        "--tolerance",
        type=_common.positive_float,
        metavar="PERCENT",
        default=100 * DEFAULT_TOLERANCE,
        help="photon bias beyond which the tool is off, %% (default %(default)g)",
    )
    p.add_argument(
        "--offset-tolerance",
        type=_common.positive_float,
        metavar="ADU",
        help="baseline error beyond which the tool is off (default: the "
        "calibrated offset's spread over pixels plus 1 ADU)",
    )
    _common.add_quiet(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from ..export.audit import audit

    with _common.recording_warnings() as caught:
        found = audit(
            args.toolfile,
            _common.calibration_of(args, args.setpoint),
            setpoint=args.setpoint,
            tool=args.tool,
            tool_gain=args.tool_gain,
            qe=args.qe,
            tolerance=args.tolerance / 100,
            offset_tolerance=args.offset_tolerance,
        )
    off = [a for a in found if not a.ok]
    if not args.quiet or off:
        for a in found:
            print("\n".join(a.lines()))
        if len(found) > 1:
            print(f"{len(found) - len(off)} of {len(found)} entries agree with the calibration")
    _common.print_warnings(caught)
    return 1 if off else 0
