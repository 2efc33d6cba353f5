"""``emccdcal plan``: what to record (light, set-points, frames, darks) to reach a target
precision, from the Fisher information of the likelihood; ``--check PLAN`` predicts what
an edited plan gives."""

from __future__ import annotations

from pathlib import Path

from .. import defaults
from . import _common


def add_parser(subparsers):
    p = subparsers.add_parser(
        "plan",
        help="what to record to reach a target precision (light, frames, darks)",
        description="Plan a calibration: from a rough description of the camera and a "
        "target precision, the light level, the frames at each set-point (or level) and "
        "the dark frames that reach it with the fewest frames, with the standard error "
        "predicted for every estimate. Predicted from the Fisher information of the "
        "likelihood calibrate uses; writes plan.toml, which acquire records and a person "
        "can edit (then --check it).",
    )
    p.add_argument(
        "--check",
        type=Path,
        default=None,
        metavar="PLAN",
        help="predict the precision of an existing (edited) plan.toml instead",
    )
    cam = p.add_argument_group("the camera, roughly (a data sheet or a previous result)")
    cam.add_argument(
        "--e-per-adu",
        type=_common.number_or_path,
        default=None,
        metavar="PHI",
        help="ADU conversion factor, e-/ADU, or a result whose median phi, "
        "offset and read noise are used",
    )
    cam.add_argument(
        "--read-noise",
        type=_common.positive_float,
        default=None,
        metavar="ADU",
        help="read noise, ADU",
    )
    cam.add_argument(
        "--offset", type=float, default=None, metavar="ADU", help="offset (bias) level, ADU"
    )
    cam.add_argument(
        "--adc-bits",
        type=_common.positive_int,
        default=16,
        metavar="B",
        help="ADC bit depth (default 16)",
    )
    cam.add_argument(
        "--pixel-well",
        type=_common.positive_float,
        default=None,
        metavar="E",
        help="the pixel's full well, e- (data sheet): the light stays below it",
    )
    cam.add_argument(
        "--register-well",
        type=_common.positive_float,
        default=None,
        metavar="E",
        help="the EM register's full well, e- (data sheet): the multiplied charge stays below it",
    )
    cam.add_argument(
        "--setpoints",
        type=_common.number_list,
        default=[1, 5, 25, 100, 300],
        metavar="G,G,...",
        help="the set-points to calibrate, 1 included (default 1,5,25,100,300)",
    )
    cam.add_argument(
        "--em-gain",
        type=_common.number_list,
        default=None,
        metavar="G,G,...",
        help="the true gains to assume at the set-points (default: the set-points themselves)",
    )
    _common.add_em_model(p, auto=False)
    _common.add_device(p)
    _add_what(p)
    _common.add_out(
        p, "the folder to write plan.toml into, or the plan's own .toml path", required=False
    )
    _common.add_quiet(p)
    p.set_defaults(func=run)
    return p


def _add_what(p) -> None:
    """The calibration's options: its method, the targets and the limits."""
    what = p.add_argument_group("the calibration")
    what.add_argument(
        "--method",
        choices=defaults.PLAN_METHODS,
        default=None,
        help="gs: a gain series (phi known); is-adu: an intensity series at "
        "1x (measures phi); is-gain: one at --setpoint (default gs; is-adu for a "
        "--camera-kind without an EM register)",
    )
    what.add_argument(
        "--camera-kind",
        choices=defaults.CAMERA_KINDS,
        default=None,
        help="the kind of camera, recorded in the plan (acquire --simulated records from "
        "a simulated one of that kind; scmos, qcmos and ccd have no EM register)",
    )
    what.add_argument(
        "--setpoint",
        type=_common.positive_float,
        default=None,
        metavar="G",
        help="the set-point of an is-gain series (default the highest)",
    )
    what.add_argument(
        "--target-se",
        type=_common.positive_float,
        default=0.5,
        metavar="PERCENT",
        help="relative standard error per pixel of every "
        "em_gain (of e_per_adu for is-adu), percent (default 0.5)",
    )
    what.add_argument(
        "--target-read-noise-se",
        type=_common.positive_float,
        default=None,
        metavar="PERCENT",
        help="relative standard error per pixel of the read-noise variance from the darks, "
        "percent (a localization tool's variance map; Huang et al. record ~20000 darks: "
        "1 %%): the dark frames are at least what reaches it",
    )
    what.add_argument(
        "--max-frames",
        type=_common.positive_int,
        default=None,
        metavar="N",
        help="most frames of one stack",
    )
    what.add_argument(
        "--frame-rate",
        type=_common.positive_float,
        default=None,
        metavar="HZ",
        help="frames per second, for the recording time",
    )


def _camera_from(args):
    """φ, offset and read noise: as given, else an earlier result's medians."""
    from ..errors import OptionError

    phi, offset, noise = args.e_per_adu, args.offset, args.read_noise
    if isinstance(phi, Path):
        from ..acquire.plan import camera_of

        known = camera_of(phi)
        phi = known["e_per_adu"]
        offset = known["offset"] if offset is None else offset
        noise = known["read_noise"] if noise is None else noise
    missing = [
        name
        for name, v in (("--e-per-adu", phi), ("--read-noise", noise), ("--offset", offset))
        if v is None
    ]
    if missing:
        raise OptionError(
            f"plan needs {', '.join(missing)} (a data sheet's values do; or "
            "--e-per-adu RESULT of an earlier calibration)"
        )
    return phi, offset, noise


def run(args) -> int:
    from .._output import atomic_write_text
    from ..acquire.plan import plan
    from ..acquire.plan_file import plan_text, read_plan

    if args.check is not None:
        result = read_plan(args.check)
    else:
        phi, offset, noise = _camera_from(args)
        method = args.method
        if method is None:
            method = "is-adu" if args.camera_kind in defaults.WITHOUT_EM_REGISTER else "gs"
        result = plan(
            method=method,
            camera_kind=args.camera_kind,
            e_per_adu=phi,
            read_noise=noise,
            offset=offset,
            adc_bits=args.adc_bits,
            setpoints=args.setpoints,
            em_gain=args.em_gain,
            setpoint=args.setpoint,
            target_se=args.target_se,
            em_model=args.em_model or defaults.DEFAULT_EM_MODEL,
            stages=args.stages,
            pixel_well=args.pixel_well,
            register_well=args.register_well,
            max_frames=args.max_frames,
            frame_rate_hz=args.frame_rate,
            device=args.device,
            read_noise_target_se=args.target_read_noise_se,
        )
    if not args.quiet:
        print(table(result))
    if args.out is not None:
        out = Path(args.out)
        out = out if out.suffix.lower() == ".toml" else out / "plan.toml"
        with _common.output(args, out, kind="file"):
            atomic_write_text(out, plan_text(result))
        if not args.quiet:
            print(f"wrote {out}")
    return 0 if result.reached or args.check is not None else 1


def table(p) -> str:
    """The plan as the console prints it."""
    from .._util import format_setpoint  # not result's import: it loads xarray

    worst = "e_per_adu" if p.method == "is-adu" else "em_gain"
    lines = []
    if p.method == "gs":
        lines.append(
            f"light: {p.photoelectrons:.1f} e- per pixel per frame at 1x; "
            f"dark frames: {p.dark_frames} per set-point (shutter closed)"
        )
        lines.append(
            f"{'set-point':>9}  {'frames':>7}  {'SE em_gain':>10}  {'SE photoelectrons':>17}"
        )
        for a in p.acquisitions:
            g = a.predicted_se.get("em_gain")
            e = a.predicted_se.get("photoelectrons")
            lines.append(
                f"{format_setpoint(a.setpoint) + 'x':>9}  {a.frames:>7}  "
                f"{'' if g is None else f'{g:.3f} %':>10}  "
                f"{'' if e is None else f'{e:.3f} %':>17}"
            )
    else:
        lines.append(
            f"intensity series at {format_setpoint(p.acquisitions[0].setpoint)}x; "
            f"dark frames: {p.dark_frames} (one stack, shutter closed; SE of the read-noise "
            f"variance {p.read_noise_variance_se:.2f} %)"
        )
        lines.append(f"{'light (e-/px/frame)':>19}  {'frames':>7}  {'SE photoelectrons':>17}")
        for a in p.acquisitions:
            lines.append(
                f"{a.photoelectrons:>19.1f}  {a.frames:>7}  "
                f"{a.predicted_se['photoelectrons']:>15.3f} %"
            )
    total = f"total {p.total_frames} frames"
    if p.seconds is not None:
        total += f", {p.seconds / 60:.1f} min at {p.frame_rate_hz:g} Hz"
    lines.append(total)
    verdict = f"predicted SE of {worst} per pixel: {p.predicted_se:.3f} % (worst)"
    if p.target_se == p.target_se:  # a target was set
        if p.reached:
            verdict += f"; target {p.target_se:g} % reached"
        elif p.max_frames is not None:
            verdict += (
                f"; target {p.target_se:g} % NOT reached within {p.max_frames} "
                "frames per stack: allow more frames (--max-frames) or a larger target"
            )
        else:
            from ..acquire.plan import dark_limited

            exact = dark_limited(p)
            if exact is not None:
                verdict += (
                    f"; target {p.target_se:g} % NOT reached: the {p.dark_frames} dark "
                    f"frames limit it ({exact:.3f} % with exact maps): record more "
                    "dark frames (dark_frames), not more light"
                )
            else:
                verdict += (
                    f"; target {p.target_se:g} % NOT reached: record more frames "
                    "where the SE is highest (or plan again)"
                )
    lines.append(verdict)
    return "\n".join(lines)
