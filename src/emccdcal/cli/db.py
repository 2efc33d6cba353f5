"""``emccdcal db add|list|show|compare``: the calibration database (SQLite)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from . import _common


def add_parser(subparsers):
    p = subparsers.add_parser(
        "db",
        help="the calibration database: add, list, show, compare (ageing)",
        description="Keep every calibration of a lab's cameras in one SQLite file, keyed by "
        "camera serial and read-out state, and follow each set-point's gain over time.",
    )
    _db_options(p)
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    a = sub.add_parser("add", help="add a calibration result")
    a.add_argument(
        "result",
        metavar="RESULT",
        help="calibration.nc or its directory (several joined by commas)",
    )
    a.add_argument("--camera", metavar="SERIAL", help="serial (default: what the files record)")
    a.add_argument(
        "--readout",
        metavar="TEXT",
        help="read-out state (default: the recorded rate, analog gain, ADC bits)",
    )
    a.add_argument(
        "--date",
        metavar="ISO",
        help="when the data were taken (default: the result's creation time)",
    )
    a.add_argument("--note", default="", help="free text kept with the entry")
    ls = sub.add_parser("list", help="list the entries")
    ls.add_argument("--camera", metavar="SERIAL", help="only this camera's entries")
    ls.add_argument("--json", action="store_true", help="print JSON")
    sh = sub.add_parser("show", help="one entry in full (JSON)")
    sh.add_argument("id", type=int, help="the entry's id (emccdcal db list)")
    c = sub.add_parser(
        "compare",
        help="gain against date per set-point, calibrations and "
        "gain checks; flag ageing, changes and trends",
    )
    c.add_argument("--camera", metavar="SERIAL", required=True, help="the camera's serial")
    c.add_argument(
        "--readout", metavar="TEXT", help="its read-out state, where it has calibrations in several"
    )
    c.add_argument(
        "--max-age",
        type=_common.positive_float,
        metavar="DAYS",
        help="flag a newest calibration older than DAYS",
    )
    c.add_argument(
        "--z",
        type=_common.positive_float,
        default=3.0,
        help="flag a gain change beyond z combined SEs (default %(default)s)",
    )
    c.add_argument("-o", "--out", type=Path, metavar="DIR", help="write the figure here")
    _common.add_overwrite(c)
    rm = sub.add_parser("remove", help="remove an entry (its result files stay)")
    rm.add_argument("id", type=int, help="the entry's id (emccdcal db list)")
    mv = sub.add_parser("relocate", help="point an entry at its moved result")
    mv.add_argument("id", type=int, help="the entry's id (emccdcal db list)")
    mv.add_argument("result", metavar="RESULT", help="the result at its new place")
    for s in (a, ls, sh, c, rm, mv):  # the options are taken after the action too
        _db_options(s, suppress=True)
    p.set_defaults(func=run)
    return p


def _db_options(p, *, suppress: bool = False) -> None:
    import argparse

    default = {"default": argparse.SUPPRESS} if suppress else {}
    p.add_argument(
        "--db",
        type=Path,
        metavar="PATH",
        **default,
        help="database file (default: $EMCCDCAL_DB, else calibrations.sqlite in "
        "the user's data directory)",
    )
    p.add_argument(
        "-q", "--quiet", action="store_true", **default, help="no progress bars, no summary"
    )


def run(args) -> int:
    from .._output import comment
    from ..export import database

    if args.action == "add":
        with _common.recording_warnings() as caught:
            e = database.add(
                args.result,
                db=args.db,
                camera=args.camera,
                readout=args.readout,
                date=args.date,
                note=args.note,
            )
        _common.print_warnings(caught)
        if not args.quiet:
            print(
                f"added entry {e.id}: camera {comment(e.camera)} "
                f"({comment(e.readout or 'read-out not recorded')}), {e.date[:10]}, {e.method}, "
                "set-points " + ", ".join(f"{s:g}x" for s in sorted(e.gains))
            )
        return 0
    if args.action == "list":
        found = database.entries(db=args.db, camera=args.camera)
        if args.json:
            print(json.dumps([e.as_dict() for e in found], indent=2))
            return 0
        print(f"{'id':>4}  {'camera':<14} {'date':<10}  {'method':<14} readout / gains")
        for e in found:
            gains = ", ".join(f"{s:g}x {m:.4g}" for s, (m, _, _) in sorted(e.gains.items()))
            print(
                f"{e.id:>4}  {comment(e.camera):<14} {comment(e.date[:10]):<10}  "
                f"{e.method:<14} {comment(e.readout or '-')} / {gains}"
            )
        return 0
    if args.action in ("remove", "relocate"):
        e = (
            database.remove(args.id, db=args.db)
            if args.action == "remove"
            else database.relocate(args.id, args.result, db=args.db)
        )
        if not args.quiet:
            print(
                f"{'removed' if args.action == 'remove' else 'relocated'} entry {e.id}: "
                f"camera {comment(e.camera)}, {e.date[:10]}, {comment(e.path)}"
            )
        return 0
    if args.action == "show":
        e, summary = database.entry(args.id, db=args.db, with_summary=True)
        print(json.dumps({**e.as_dict(), "summary": summary}, indent=2))
        return 0
    found, findings = database.compare(
        args.camera, db=args.db, readout=args.readout, max_age_days=args.max_age, z=args.z
    )
    checked = database.checks(db=args.db, camera=args.camera, readout=found[-1].readout)
    lines = [
        f"{'id':>4}  {'date':<10}  {'register':<8}  set-point: gain ± the standard error "
        "of the sensor's gain (se_of_median)"
    ]
    lines += [
        f"{e.id:>4}  {e.date[:10]}  {e.register:<8}  "
        + ", ".join(f"{s:g}x {m:.4g} ± {se or 0:.2g}" for s, (m, se, _) in sorted(e.gains.items()))
        for e in found
    ]
    if checked:
        lines.append("gain checks from dark frames (emccdcal gain-check --record):")
        lines += [
            f"{'c' + str(c.id):>4}  {c.date[:10]}  {c.register:<8}  {c.setpoint:g}x "
            f"{c.em_gain:.4g} ± {c.se:.2g}"
            for c in checked
        ]
    if args.out is not None:
        from .._output import slug
        from ..report.figures import gain_history_figure, save_figure

        with _common.output(args, args.out):  # the serial is data: never a path
            lines += [
                f"wrote {f}"
                for f in save_figure(
                    gain_history_figure(found, camera=args.camera, checks=checked),
                    args.out / f"gain-history-{slug(args.camera)}",
                )
            ]
    if not args.quiet:
        print("\n".join(lines))
    for f in findings:
        print(f"warning: {comment(f.message)}", file=sys.stderr)
    return 1 if findings else 0
