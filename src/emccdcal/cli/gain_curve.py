"""``emccdcal gain-curve RESULT... -o DIR``: the gain as a smooth function of the set-point."""

from __future__ import annotations

from pathlib import Path

from . import _common


def add_parser(subparsers):
    p = subparsers.add_parser(
        "gain-curve",
        help="fit the gain against the set-point; predict set-points not measured",
        description="Fit the measured EM gain (median over converged pixels) as a smooth "
        "monotone function of the set-point, with a 95 % band, and predict gains at "
        "set-points not measured. Writes gain-curve.csv, gain-curve.json and the figure; "
        "export and apply take gain-curve.json (--gain-curve) for a set-point the "
        "calibration did not measure.",
    )
    p.add_argument(
        "results",
        nargs="+",
        type=Path,
        metavar="RESULT",
        help="calibration results (files or directories); their set-points pool",
    )
    _common.add_out(p)
    p.add_argument(
        "--predict",
        type=_common.number_list,
        default=[],
        metavar="G,G,...",
        help="set-points to predict (besides the measured ones)",
    )
    _common.add_accept_mismatch(p)
    _common.add_no_figures(p)
    _common.add_quiet(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    import json

    import numpy as np

    from .._output import atomic_write_text
    from ..export.gain_curve import fit_gain_curve
    from ..result import format_setpoint, result_files

    out = Path(args.out)
    names = ("gain-curve.csv", "gain-curve.json")
    with (
        _common.recording_warnings() as caught,
        _common.output(args, out, inputs=result_files(args.results), names=names),
    ):
        curve = fit_gain_curve(args.results, accept_mismatch=args.accept_mismatch)
        table = curve.predict(sorted(set(curve.setpoints) | set(args.predict)))
        lines = [
            "setpoint,gain,se_of_median,lower95,upper95,measured_gain,"
            "measured_se_of_median,extrapolated"
        ]
        for i, s in enumerate(table["setpoint"]):
            at = np.flatnonzero(curve.setpoints == s)
            meas = f"{curve.gains[at[0]]:.6g},{curve.gain_se[at[0]]:.4g}" if at.size else ","
            lines.append(
                f"{format_setpoint(s)},{table['gain'][i]:.6g},{table['se_of_median'][i]:.4g},"
                f"{table['lower'][i]:.6g},{table['upper'][i]:.6g},{meas},"
                f"{str(bool(table['extrapolated'][i])).lower()}"
            )
        doc = curve.as_dict()
        written = [
            atomic_write_text(out / names[0], "\n".join(lines) + "\n"),
            atomic_write_text(out / names[1], json.dumps(doc, indent=2) + "\n"),
        ]
        if not args.no_figures:
            from ..report.figures import gain_curve_figure, save_figure

            written += save_figure(
                gain_curve_figure(curve, predict=args.predict), out / "gain-curve"
            )
    if not args.quiet:
        print("\n".join(lines))
        for f in written:
            print(f"wrote {f}")
    _common.print_warnings(caught)
    return 0
