"""``emccdcal gain-check DARKS... --e-per-adu PHI|RESULT``: the true EM gain from dark
frames alone, whether it still agrees with its calibration, and its record in the
calibration database."""

from __future__ import annotations

from pathlib import Path

from ..defaults import DEFAULT_EM_MODEL
from . import _common

#: The files ``-o OUT`` receives.
RECORD_FILE = "gain-check.json"
FIGURE_STEM = "gain-check"


def add_parser(subparsers):
    p = subparsers.add_parser(
        "gain-check",
        help="the EM gain from dark frames alone, against its calibration",
        description="The true EM gain at a set-point from shutter-closed frames: their "
        "clock-induced-charge and dark-current electrons pass the whole register and "
        "their multiplied events, with phi known, show the gain. Maximum likelihood under "
        "the register model, each pixel's offset and read noise its own, the gain (and "
        "the event rate) shared by the pixels, the bias of the pixels' own parameters "
        "removed; with its standard error. Exit 1 when the gain differs from its "
        "calibration (--calibration RESULT, or --camera SERIAL from the database) beyond "
        "--z combined SEs.",
    )
    p.add_argument(
        "darks",
        nargs="+",
        type=Path,
        metavar="DARKS",
        help="dark stacks of one set-point and read-out mode (any format)",
    )
    p.add_argument(
        "--e-per-adu",
        type=_common.number_or_path,
        default=None,
        metavar="PHI",
        help="ADU conversion factor of the read-out mode, e-/ADU, or a result "
        "whose median phi is used (default: the calibration's)",
    )
    p.add_argument(
        "--setpoint",
        type=_common.positive_float,
        default=None,
        metavar="G",
        help="the frames' EM-gain set-point (default: what their file records)",
    )
    _common.add_calibration_source(p, option=True)
    p.add_argument(
        "--z",
        type=_common.positive_float,
        default=3.0,
        help="flag a difference beyond z combined SEs (default %(default)s)",
    )
    p.add_argument(
        "--record",
        action="store_true",
        help="add the check to the calibration database (--db), under --camera or "
        "the serial the frames record, for 'emccdcal db compare'",
    )
    p.add_argument(
        "--date", metavar="ISO", help="when the darks were taken, for --record (default: now)"
    )
    p.add_argument(
        "--target-se",
        type=_common.positive_float,
        default=None,
        metavar="PERCENT",
        help="the precision wanted: say how many frames would reach it when the data fall short",
    )
    p.add_argument(
        "--region",
        type=_common.region,
        default=None,
        metavar="R0:R1,C0:C1",
        help="use only these rows and columns (pixels known to be dark: "
        "masked rows, overscan or prescan columns), Python slices",
    )
    _common.add_em_model(p, auto=False)
    _common.add_device(p)
    p.add_argument(
        "--fit-register-cic",
        action="store_true",
        help="fit the clock-induced charge made inside the register (cascade)",
    )
    p.add_argument(
        "--per-pixel-rate",
        action="store_true",
        help="each pixel its own event rate (default: one shared rate)",
    )
    p.add_argument(
        "--no-bias-correction",
        action="store_true",
        help="the maximum-likelihood gain itself, without removing the bias that "
        "each pixel's own offset and read noise put into it (docs/gain-check.md)",
    )
    p.add_argument(
        "-o",
        "--out",
        type=Path,
        default=None,
        metavar="OUT",
        help=f"write {RECORD_FILE} and the figure (the pooled histogram of the "
        "darks with the fitted model) into this folder",
    )
    _common.add_overwrite(p)
    _common.add_no_figures(p)
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    _common.add_quiet(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    import contextlib
    import json

    from ..data.stacks import read_stack, stack_settings
    from ..export.gain_check import compare, verdict
    from ..errors import InputError
    from ..fit.darkgain import check_gain

    from .. import identity

    recorded = [(path, stack_settings(path, setpoint_from_name=True)) for path in args.darks]
    settings = [s for _, s in recorded]
    setpoint = _setpoint(args, settings)
    calibration = _common.calibration_of(args, setpoint) if args.results or args.camera else None
    # one camera, read-out state and set-point, and the calibration's
    identity.check(
        None if calibration is None else calibration.identity(),
        recorded,
        label="" if calibration is None else calibration.label,
        setpoint=setpoint,
        accept=args.accept_mismatch,
        what="dark stacks",
    )
    phi = _phi(args, calibration)
    if args.record or args.date is not None:  # refused now, not after the fit
        _check_record(args, settings)
    bits = {s.adc_bits for s in settings} - {None}
    outputs = (RECORD_FILE,) + (
        () if args.no_figures else (f"{FIGURE_STEM}.png", f"{FIGURE_STEM}.svg")
    )
    with (
        _common.output(args, args.out, inputs=args.darks, names=outputs)
        if args.out is not None
        else contextlib.nullcontext()
    ):
        stacks = [read_stack(path) for path in args.darks]
        try:
            check = check_gain(
                stacks,
                phi,
                setpoint=setpoint,
                em_model=args.em_model or DEFAULT_EM_MODEL,
                stages=args.stages,
                fit_register_cic=args.fit_register_cic,
                pooled_rate=not args.per_pixel_rate,
                bias_correction=not args.no_bias_correction,
                adc_max=2 ** max(bits) - 1 if bits else None,
                region=args.region,
                histogram=args.out is not None and not args.no_figures,
                progress=not (args.quiet or args.json),
                device=args.device,
            )
        except InputError as exc:  # the data as a whole: named by their files
            names = ", ".join(f"'{path}'" for path in args.darks)
            raise InputError(f"{names}: {exc}") from None
        against = compare(check, calibration, z=args.z) if calibration is not None else None
        record = {**check.as_dict(), **({"calibration": against} if against else {})}
        written = _write(args, check, record) if args.out is not None else []
    recorded = _record(args, check, settings) if args.record else None
    if args.json:
        print(
            json.dumps(
                {**record, **({"database_check": recorded.id} if recorded else {})}, indent=2
            )
        )
    elif not args.quiet or (against is not None and against["changed"]):
        print(check.summary(None if args.target_se is None else args.target_se / 100))
        if against is not None:
            print(verdict(against))
        if not args.quiet:
            for path in written:
                print(f"wrote {path}")
            if recorded is not None:
                print(
                    f"recorded as check {recorded.id} of camera {recorded.camera} in the "
                    "calibration database"
                )
    return 1 if against is not None and against["changed"] else 0


def _setpoint(args, settings):
    from ..errors import OptionError

    if args.setpoint is not None:
        return args.setpoint
    recorded = {s.em_gain_setpoint for s in settings}
    if recorded == {None}:
        raise OptionError(
            "the dark stacks record no EM gain set-point (nor do their names state one): "
            "give --setpoint"
        )
    if len(recorded) != 1 or None in recorded:
        said = ", ".join("none" if g is None else f"{g:g}" for g in sorted(recorded, key=str))
        raise OptionError(
            f"the dark stacks record different set-points ({said}): give --setpoint, "
            "and stacks of one set-point"
        )
    return recorded.pop()


def _phi(args, calibration) -> float:
    """φ: ``--e-per-adu`` (a number, or a result's median), else the calibration's."""
    from ..errors import OptionError

    if isinstance(args.e_per_adu, float):
        return args.e_per_adu
    if isinstance(args.e_per_adu, Path):  # a result's φ: its median over pixels
        from ..export.gain_check import e_per_adu_of
        from ..result import load_calibration

        return e_per_adu_of(load_calibration(args.e_per_adu))
    if calibration is None:
        raise OptionError(
            "give --e-per-adu PHI (or a result), or the calibration: "
            "--calibration RESULT or --camera SERIAL"
        )
    from ..export.gain_check import e_per_adu_of

    return e_per_adu_of(calibration)


def _write(args, check, record) -> list[Path]:
    """``gain-check.json`` and, unless ``--no-figures``, the figure, into ``-o OUT``."""
    import json

    from .._output import atomic_write_text

    written = [args.out / RECORD_FILE]
    atomic_write_text(written[0], json.dumps(record, indent=2, allow_nan=False) + "\n")
    if not args.no_figures:
        from ..report.figures import gain_check_figure, save_figure

        written.append(save_figure(gain_check_figure(check), args.out / FIGURE_STEM)[0])
    return written


def _check_record(args, settings) -> None:
    """What ``--record`` and ``--date`` need, checked before any fitting."""
    from ..errors import OptionError
    from ..export import database

    if args.date is not None:
        if not args.record:
            raise OptionError("--date is when the darks were taken, for --record")
        database.past_date(args.date)
    serials = {s.serial for s in settings} - {None}
    if args.camera is None and len(serials) != 1:
        raise OptionError(
            "--record needs the camera: the dark stacks record "
            f"{'no serial' if not serials else 'several serials'}; give "
            "--camera SERIAL"
        )


def _record(args, check, settings):
    """The check in the calibration database, under the camera's serial and the read-out
    state its calibrations are keyed by."""
    from ..export import database

    serials = {s.serial for s in settings} - {None}
    camera = args.camera or (serials.pop() if len(serials) == 1 else None)
    readout = args.readout
    if readout is None:
        found = database.entries(db=args.db, camera=camera) if camera else []
        states = {e.readout for e in found}
        readout = states.pop() if len(states) == 1 else ""
    return database.add_check(check, camera=camera, readout=readout, date=args.date, db=args.db)
