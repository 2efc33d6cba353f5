"""``emccdcal gain-check DARKS... --e-per-adu PHI|RESULT``: the true EM gain from dark
frames alone, and whether it still agrees with its calibration."""

from __future__ import annotations

from pathlib import Path

from . import _common


def add_parser(subparsers):
    p = subparsers.add_parser(
        "gain-check",
        help="the EM gain from dark frames alone, against its calibration",
        description="The true EM gain at a set-point from shutter-closed frames: their "
        "clock-induced-charge and dark-current electrons pass the whole register and "
        "their multiplied events, with phi known, show the gain. Maximum likelihood under "
        "the register model, each pixel's offset and read noise its own, the gain (and "
        "the event rate) shared by the pixels; with its standard error. Exit 1 when the "
        "gain differs from --calibration's beyond --z combined SEs.",
    )
    p.add_argument("darks", nargs="+", type=Path, metavar="DARKS",
                   help="dark stacks of one set-point and read-out mode (any format)")
    p.add_argument("--e-per-adu", type=_common.number_or_path, default=None, metavar="PHI",
                   help="ADU conversion factor of the read-out mode, e-/ADU, or a result "
                   "whose median phi is used (default: --calibration's)")
    p.add_argument("--setpoint", type=_common.positive_float, default=None, metavar="G",
                   help="the frames' EM-gain set-point (default: what their file records)")
    p.add_argument("--calibration", type=Path, default=None, metavar="RESULT",
                   help="compare with this calibration's gain at the set-point")
    p.add_argument("--z", type=_common.positive_float, default=3.0,
                   help="flag a difference beyond z combined SEs (default %(default)s)")
    p.add_argument("--target-se", type=_common.positive_float, default=None,
                   metavar="PERCENT", help="the precision wanted: say how many frames "
                   "would reach it when the data fall short")
    p.add_argument("--region", type=_region, default=None, metavar="R0:R1,C0:C1",
                   help="use only these rows and columns (pixels known to be dark: "
                   "masked rows, overscan or prescan columns), Python slices")
    _common.add_em_model(p, auto=False)
    p.add_argument("--fit-register-cic", action="store_true",
                   help="fit the clock-induced charge made inside the register (cascade)")
    p.add_argument("--per-pixel-rate", action="store_true",
                   help="each pixel its own event rate (default: one shared rate)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    _common.add_quiet(p)
    p.set_defaults(func=run)
    return p


def _region(text: str):
    import argparse

    try:
        parts = text.split(",")
        if len(parts) != 2 or any(part.count(":") != 1 for part in parts):
            raise ValueError(text)
        rows, cols = (tuple(int(v) if v else None for v in part.split(":")) for part in parts)
        return slice(*rows), slice(*cols)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected rows and columns as R0:R1,C0:C1, got {text!r}") from None


def run(args) -> int:
    import json

    from ..data.stacks import load_stack, stack_settings
    from ..errors import OptionError
    from ..export.gain_check import compare
    from ..fit.darkgain import check_gain

    phi = args.e_per_adu if args.e_per_adu is not None else args.calibration
    if phi is None:
        raise OptionError("give --e-per-adu PHI (or a result), or --calibration RESULT")
    if isinstance(phi, Path):
        from ..acquire.plan import camera_of

        phi = camera_of(phi)["e_per_adu"]
    settings = [stack_settings(path) for path in args.darks]
    setpoint = args.setpoint
    if setpoint is None:
        recorded = {s.em_gain_setpoint for s in settings}
        if len(recorded) != 1 or None in recorded:
            raise OptionError(f"the dark stacks record set-point(s) {sorted(map(str, recorded))}: "
                              "give --setpoint")
        setpoint = recorded.pop()
    bits = {s.adc_bits for s in settings} - {None}
    check = check_gain([load_stack(path) for path in args.darks], phi, setpoint=setpoint,
                       em_model=args.em_model or "cascade", stages=args.stages,
                       fit_register_cic=args.fit_register_cic,
                       pooled_rate=not args.per_pixel_rate,
                       adc_max=2 ** max(bits) - 1 if bits else None, region=args.region,
                       progress_bars=not (args.quiet or args.json))
    against = compare(check, args.calibration, z=args.z) if args.calibration else None
    if args.json:
        print(json.dumps({**check.as_dict(), **({"calibration": against} if against else {})},
                         indent=2))
    else:
        print(_line(check, args.target_se))
        if against is not None:
            print(_verdict(against))
    return 1 if against is not None and against["changed"] else 0


def _line(check, target_se) -> str:
    text = (f"em_gain {check.em_gain:.4g} ± {check.em_gain_se:.2g} "
            f"({100 * check.relative_se:.2g} %) at set-point {check.setpoint:g}, from "
            f"{check.events:.0f} events ({check.pixels} px × {check.frames} frames, "
            f"{check.event_rate:.3g} e-/px/frame; {check.em_model}, phi {check.e_per_adu:.4g} "
            "e-/ADU)")
    if target_se is not None and 100 * check.relative_se > target_se:
        text += (f"; {target_se:g} % needs about {check.frames_for(target_se / 100)} frames "
                 "of these pixels")
    return text


def _verdict(c: dict) -> str:
    diff = f"{c['difference_percent']:+.2g} ± {c['difference_se_percent']:.2g} %"
    if not c["changed"]:
        return (f"agrees with its calibration of {c['calibrated']} "
                f"({c['calibrated_em_gain']:.4g}): {diff}")
    side = "above" if c["difference_percent"] > 0 else "below"
    return (f"the gain is {abs(c['difference_percent']):.2g} ± "
            f"{c['difference_se_percent']:.2g} % {side} its calibration of "
            f"{c['calibrated']} ({c['calibrated_em_gain']:.4g}, z = {c['z']:+.1f}): "
            "recalibrate")
