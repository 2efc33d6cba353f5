"""``emccdcal acquire``: record a plan through Micro-Manager (a real camera from its
configuration file, or the simulated EMCCD), into a session folder that ``scan`` reads."""

from __future__ import annotations

import sys
from pathlib import Path

from . import _common


def add_parser(subparsers):
    p = subparsers.add_parser(
        "acquire",
        help="record a plan through Micro-Manager (or the simulated EMCCD)",
        description="Record plan.toml (from emccdcal plan) through Micro-Manager with "
        "pymmcore-plus (the 'acquire' extra): at each set-point the dark frames with the "
        "shutter closed, then the light frames, checked first against the plan's light. "
        "Each stack is an OME-Zarr recording the camera's settings, so that 'emccdcal scan "
        "SESSION' writes the manifest. Ctrl-C keeps what was recorded; --resume goes on.",
    )
    p.add_argument("plan", type=Path, metavar="PLAN", help="the plan (plan.toml)")
    _common.add_out(p, "the session folder (new, or the one to --resume)", overwrite=False)
    src = p.add_argument_group("the camera (one of)")
    src.add_argument(
        "--mm-config",
        type=Path,
        default=None,
        metavar="FILE",
        help="a Micro-Manager configuration file (device adapters are found "
        "as pymmcore-plus finds them: MICROMANAGER_PATH, 'mmcore install')",
    )
    src.add_argument(
        "--camera",
        default=None,
        metavar="LABEL",
        help="the camera's device label (default: the configuration's camera)",
    )
    src.add_argument(
        "--simulated",
        action="store_true",
        help="the built-in simulated EMCCD (the plan's camera; truth.json "
        "written beside the stacks)",
    )
    src.add_argument(
        "--seed",
        type=_common.nonnegative_int,
        default=None,
        metavar="S",
        help="seed of the simulated camera (default: one drawn and recorded)",
    )
    how = p.add_argument_group("the recording")
    how.add_argument(
        "--roi",
        type=_roi,
        default=None,
        metavar="X,Y,W,H",
        help="a region of the sensor, px (set through the core, recorded in the files)",
    )
    how.add_argument(
        "--gain-property",
        default=None,
        metavar="NAME",
        help="the camera's EM-gain property (default by adapter: Andor Gain, "
        "PVCAM/PICAM MultiplierGain, else EMGain)",
    )
    how.add_argument(
        "--light-tolerance",
        type=_common.positive_float,
        default=None,
        metavar="PERCENT",
        help="largest difference of the light from the plan's, percent (default 25)",
    )
    how.add_argument(
        "--no-light-check",
        action="store_true",
        help="record whatever the light (saturation still stops)",
    )
    how.add_argument(
        "--stop-at-target",
        action="store_true",
        help="end each multiplied set-point when a running fit reaches the "
        "plan's target SE (a gain series)",
    )
    how.add_argument(
        "--resume", action="store_true", help="continue the session in OUT where it stopped"
    )
    _common.add_quiet(p)
    p.set_defaults(func=run)
    return p


def _roi(text: str):
    import argparse

    try:
        values = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y,W,H (integers), got {text!r}") from None
    if len(values) != 4 or min(values) < 0 or min(values[2:]) < 1:
        raise argparse.ArgumentTypeError(f"expected X,Y,W,H (x, y >= 0; w, h >= 1), got {text!r}")
    return tuple(values)


def _ask_light(core, stack) -> None:
    """Asks the person at the bench to set an intensity series' next light."""
    if not sys.stdin.isatty():
        from ..errors import OptionError

        raise OptionError(
            "an intensity-series plan needs the light set by hand before each "
            "level: run acquire in a terminal"
        )
    input(
        f"set the light to {stack.photoelectrons:.4g} e- per pixel per frame for "
        f"{stack.name}, then press Enter "
    )


def run(args) -> int:
    from ..acquire import record
    from ..acquire.plan_file import read_plan
    from ..errors import OptionError

    if args.resume and not args.simulated and args.mm_config is None:
        # the session says which camera it was recorded with
        from ..acquire.session import Session

        args.simulated = Session.load(Path(args.out)).state.get("simulated") is not None
        if not args.simulated:
            raise OptionError(
                f"{args.out} was recorded with a real camera: give its --mm-config FILE to resume"
            )
    if args.simulated == (args.mm_config is not None):
        raise OptionError("give --simulated or --mm-config FILE (a real camera)")
    if args.no_light_check and args.light_tolerance is not None:
        raise OptionError("--light-tolerance and --no-light-check contradict each other")
    tolerance = (
        None
        if args.no_light_check
        else (args.light_tolerance / 100 if args.light_tolerance else record.LIGHT_TOLERANCE)
    )
    plan = read_plan(args.plan)
    core = seed = None
    if args.simulated:
        seed = args.seed if args.seed is not None else _recorded_seed(args)
    else:
        core = record.config_core(args.mm_config)
    try:
        session = record.acquire(
            plan,
            args.out,
            core=core,
            camera=args.camera,
            simulated_seed=seed,
            roi=args.roi,
            gain_prop=args.gain_property,
            light_tolerance=tolerance,
            stop_at_target=args.stop_at_target,
            resume=args.resume,
            set_light=None if args.simulated or plan.method == "gs" else _ask_light,
            progress=not args.quiet,
        )
    except record.Interrupted as exc:
        raise KeyboardInterrupt(str(exc)) from None
    finally:
        if core is not None:
            core.unloadAllDevices()
    if not args.quiet:
        for s in session.stacks:
            reached = "" if s.reached_se is None else f"; running SE {s.reached_se:.2f} %"
            print(f"{s.file}: {s.frames} frames (planned {s.planned_frames}){reached}")
        print(f"recorded {args.out}; next: emccdcal scan {args.out}")
    return 0


def _recorded_seed(args) -> int:
    """The simulated camera's seed: a resumed session's own, else one drawn."""
    if args.resume:
        from ..acquire.session import Session

        sim = Session.load(Path(args.out)).state.get("simulated") or {}
        if "seed" in sim:
            return int(sim["seed"])
    import numpy as np

    return int(np.random.SeedSequence().entropy % (2**32))
