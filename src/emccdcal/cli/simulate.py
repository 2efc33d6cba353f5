"""``emccdcal simulate gain-series|intensity-series|beads|cmos -o OUT``: data with known
truth."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from pathlib import Path

from . import _common

#: Set-points and true gains of the paper, as the help texts show them.
_PAPER = "1,5,25,100,300"
_PAPER_GAINS = "1,4.78,22.95,90.06,261.6"


def _camera_options(p: argparse.ArgumentParser, defaults: dict | None = None) -> None:
    """The fields of :class:`emccdcal.simulate.camera.Camera`, the seed and ``-q``."""
    from .. import plugins
    from ..defaults import CAMERA_SIMULATION

    d = CAMERA_SIMULATION | (defaults or {})
    cam = p.add_argument_group("camera")
    cam.add_argument(
        "--rows", type=int, default=d["rows"], help="frame rows, px (default %(default)s)"
    )
    cam.add_argument(
        "--cols", type=int, default=d["cols"], help="frame columns, px (default %(default)s)"
    )
    cam.add_argument(
        "--frames", type=int, default=d["frames"], help="frames per stack (default %(default)s)"
    )
    cam.add_argument(
        "--dark-frames",
        type=int,
        default=d["dark_frames"],
        help="frames per dark stack (default: "
        + ("--frames)" if d["dark_frames"] is None else "%(default)s)"),
    )
    cam.add_argument(
        "--e-per-adu", type=float, default=d["e_per_adu"], help="phi, e-/ADU (default %(default)s)"
    )
    cam.add_argument(
        "--offset",
        type=float,
        default=d["offset"],
        help="offset at set-point 1, ADU (default %(default)s)",
    )
    cam.add_argument(
        "--offset-drop",
        type=float,
        default=d["offset_drop"],
        help="offset drop per decade of set-point, ADU (default %(default)s; 0 for none)",
    )
    cam.add_argument(
        "--offset-spread",
        type=float,
        default=d["offset_spread"],
        help="SD of the fixed per-pixel offset pattern, ADU (default %(default)s)",
    )
    cam.add_argument(
        "--read-noise",
        type=float,
        default=d["read_noise"],
        help="sigma of the Gaussian read-out noise before rounding, ADU (default %(default)s)",
    )
    cam.add_argument(
        "--multiplication",
        **_common.plugin_choice(plugins.REGISTERS, "register model"),
        default=d["multiplication"],
        help="EM register model: the exact Bernoulli cascade of a real camera, or "
        "the paper's gamma approximation (default %(default)s)",
    )
    cam.add_argument(
        "--stages", type=int, default=d["stages"], help="cascade stages (default %(default)s)"
    )
    cam.add_argument(
        "--cascade-method",
        choices=("pmf", "stages"),
        default=d["cascade_method"],
        help="exact cascade sampler: pmf tables (fast) or stage-by-stage binomials "
        "(default %(default)s)",
    )
    cam.add_argument(
        "--cic",
        type=float,
        default=d["cic"],
        help="clock-induced charge, e-/px/frame (default %(default)s)",
    )
    cam.add_argument(
        "--drift",
        type=float,
        default=d["drift"],
        help="illumination drift, fractional change from first to last frame (default %(default)s)",
    )
    cam.add_argument(
        "--adc-bits",
        type=int,
        default=d["adc_bits"],
        help="ADC bits; counts clip at 2^bits-1 (default %(default)s)",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        help="random seed (default: drawn and recorded in truth.json)",
    )
    _common.add_quiet(p)


def _setpoint_options(p: argparse.ArgumentParser) -> None:
    """Set-points, their true gains and offsets (gain series and beads)."""
    p.add_argument(
        "--setpoints",
        type=_common.number_list,
        default=[1.0, 5.0, 25.0, 100.0, 300.0],
        help=f"EM gain set-points, comma-separated (default {_PAPER})",
    )
    p.add_argument(
        "--em-gain",
        type=_common.number_list,
        default=None,
        help="true mean EM gain per set-point, comma-separated "
        f"(default {_PAPER_GAINS} at the paper's set-points, else the set-point)",
    )
    p.add_argument(
        "--offsets",
        type=_common.number_list,
        default=None,
        help="offset per set-point, ADU, comma-separated (overrides --offset/--offset-drop)",
    )


def _common_kwargs(args) -> dict:
    """The camera's fields, the seed and the progress switch from the parsed options."""
    from ..simulate.camera import Camera

    camera = {f.name: getattr(args, f.name) for f in dataclasses.fields(Camera)}
    return camera | {"seed": args.seed, "progress": not args.quiet}


def _report(res, what: str) -> None:
    t = res.truth
    a0 = t["acquisitions"][0]
    rows, cols = t["options"]["rows"], t["options"]["cols"]
    print(
        f"wrote {what}: {len(t['acquisitions'])} stacks of {a0['n_frames']} frames x "
        f"{rows}x{cols} px ({t['multiplication']} multiplication, seed {t['seed']})"
    )
    print(f"  manifest: {res.manifest}")
    print(f"  truth:    {res.truth_path}")
    print(f"  stacks:   {res.outdir / Path(a0['frames']).parent}{os.sep}")


#: Files every simulation writes: an earlier simulation's are refused without --overwrite.
_SIMULATED = ("manifest.toml", "truth.json")


def _run_gain_series(args) -> int:
    from ..simulate.series import simulate_gain_series

    out = _common.output_of(args)
    with _common.output(args, out, names=_SIMULATED):
        res = simulate_gain_series(
            out,
            setpoints=args.setpoints,
            em_gain=args.em_gain,
            photoelectrons=args.photoelectrons,
            offsets=args.offsets,
            **_common_kwargs(args),
        )
    _report(res, "gain series")
    return 0


def _run_intensity_series(args) -> int:
    from ..simulate.series import simulate_intensity_series

    out = _common.output_of(args)
    with _common.output(args, out, names=_SIMULATED):
        res = simulate_intensity_series(
            out,
            levels=args.levels,
            labels=args.labels,
            setpoint=args.setpoint,
            em_gain=args.em_gain,
            **_common_kwargs(args),
        )
    _report(res, "intensity series")
    return 0


def _run_beads(args) -> int:
    from ..simulate.beads import TRUTH_CALIBRATION_FILE, simulate_beads

    out = _common.output_of(args)
    with _common.output(args, out, names=_SIMULATED):
        res = simulate_beads(
            out,
            beads=args.beads,
            photoelectrons=args.photoelectrons,
            width=args.width,
            background=args.background,
            min_separation=args.min_separation,
            margin=args.margin,
            bleaching=args.bleaching,
            halo=args.halo,
            halo_width=args.halo_width,
            blinking=args.blinking,
            blink_frames=args.blink_frames,
            repeat=args.repeat,
            setpoints=args.setpoints,
            em_gain=args.em_gain,
            offsets=args.offsets,
            **_common_kwargs(args),
        )
    _report(res, "bead movies")
    print(f"  true calibration: {res.outdir / TRUTH_CALIBRATION_FILE}")
    return 0


def _run_cmos(args) -> int:
    from ..simulate.cmos import CMOSCamera, simulate_cmos_series

    out = _common.output_of(args)
    given = {
        k: getattr(args, k)
        for k in (
            "rows", "cols", "frames", "dark_frames", "e_per_adu", "read_noise_e", "dark_current"
        )
        if getattr(args, k) is not None
    }  # fmt: skip
    camera = CMOSCamera(
        kind=args.camera_kind,
        rts_fraction=args.rts_fraction,
        rts_states=args.rts_states,
        hot_fraction=args.hot_fraction,
        **given,
    )
    with _common.output(args, out, names=_SIMULATED):
        res = simulate_cmos_series(
            out,
            camera=camera,
            levels=args.levels,
            dark_exposures_s=args.dark_exposures,
            exposure_s=args.exposure,
            seed=args.seed,
            progress=not args.quiet,
        )
    t = res.truth
    stacks = (
        f"dark.tif and {len(t['levels'])} levels"
        if t["exposures_s"] is None
        else f"darks at {', '.join(f'{x:g}' for x in t['exposures_s'].values())} s, no light,"
    )
    print(
        f"wrote a {t['camera']} calibration: {stacks} of "
        f"{camera.frames} frames x {camera.rows}x{camera.cols} px (seed {t['seed']})"
    )
    print(f"  manifest: {res.manifest}")
    print(f"  truth:    {res.truth_path} and truth-*.tif")
    return 0


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add ``simulate {gain-series,intensity-series,beads,cmos}`` to the ``emccdcal``
    command line."""
    p = subparsers.add_parser(
        "simulate",
        help="write synthetic stacks, darks, a manifest and truth.json",
        description="Write synthetic EMCCD acquisitions with known truth (docs/simulation.md).",
    )

    def no_kind(args) -> int:
        p.print_usage(sys.stderr)
        print(
            "emccdcal simulate: error: choose gain-series, intensity-series, beads or cmos",
            file=sys.stderr,
        )
        return 2

    p.set_defaults(func=no_kind)
    kinds = p.add_subparsers(dest="kind", metavar="KIND")
    _add_gain_series(kinds)
    _add_intensity_series(kinds)
    _add_beads(kinds)
    _add_cmos(kinds)
    return p


def _add_cmos(kinds) -> None:
    from ..defaults import SIMULATED_CMOS

    cm = kinds.add_parser(
        "cmos",
        help="an sCMOS or qCMOS camera's dark and levels (Huang's protocol)",
        description="Simulate the calibration of a camera without an EM register: dark.tif and "
        "int1.tif ... with per-pixel phi, offset and read noise, random-telegraph pixels and "
        "the ADC's rounding (docs/cmos.md).",
    )
    _common.add_out_or_dir(cm, "output directory (created)")
    cm.add_argument(
        "--camera-kind", choices=SIMULATED_CMOS, default="scmos",
        help="which preset (default %(default)s: an ORCA-Flash-like sCMOS; qcmos: ORCA-Quest-like)",
    )  # fmt: skip
    cm.add_argument("--rows", type=int, default=None, help="frame rows, px (default 24)")
    cm.add_argument("--cols", type=int, default=None, help="frame columns, px (default 24)")
    cm.add_argument("--frames", type=int, default=None, help="frames per level (default 2000)")
    cm.add_argument("--dark-frames", type=int, default=None, help="dark frames (default: --frames)")
    cm.add_argument("--e-per-adu", type=float, default=None, help="median phi, e-/ADU (preset's)")
    cm.add_argument(
        "--read-noise-e", type=float, default=None, help="median read noise, e- (preset's)"
    )
    cm.add_argument(
        "--levels", type=_common.number_list, default=None,
        help="photoelectrons per pixel per frame of each level, e-, comma-separated",
    )  # fmt: skip
    cm.add_argument(
        "--dark-exposures",
        type=_common.number_list,
        default=None,
        metavar="S,S,...",
        help="the photon-free path: no light, dark stacks at these exposures (s), the "
        "shortest the others' dark (needs --dark-current)",
    )
    cm.add_argument(
        "--exposure",
        type=float,
        default=None,
        metavar="S",
        help="a lit series' exposure (s): the dark current's signal in the dark and every "
        "level (default: none)",
    )
    cm.add_argument(
        "--dark-current",
        type=float,
        default=None,
        help="median dark current, e- per pixel per second (default 0)",
    )
    cm.add_argument(
        "--rts-fraction", type=float, default=0.0,
        help="fraction of random-telegraph pixels (default 0)",
    )  # fmt: skip
    cm.add_argument(
        "--rts-states", type=int, default=2,
        help="offset states of a random-telegraph pixel, 4 read-noise widths apart (default 2)",
    )  # fmt: skip
    cm.add_argument(
        "--hot-fraction", type=float, default=0.0,
        help="fraction of hot pixels, 30 times the dark current (default 0; needs "
        "--dark-current)",
    )  # fmt: skip
    cm.add_argument(
        "--seed",
        type=int,
        default=None,
        help="random seed (default: drawn and recorded in truth.json)",
    )
    _common.add_quiet(cm)
    cm.set_defaults(func=_run_cmos)


def _add_gain_series(kinds) -> None:
    from ..defaults import CAMERA_SIMULATION as _DEFAULTS

    gs = kinds.add_parser(
        "gain-series",
        help="fixed illumination at several EM gain set-points",
        description="Simulate a gain series: one illumination, several EM gain set-points, "
        "with a dark stack and offset/read-noise maps per set-point.",
    )
    _common.add_out_or_dir(gs, "output directory (created)")
    _setpoint_options(gs)
    gs.add_argument(
        "--photoelectrons",
        type=float,
        default=_DEFAULTS["photoelectrons"],
        help="photoelectrons per pixel per frame, e- (default %(default)s)",
    )
    _camera_options(gs)
    gs.set_defaults(func=_run_gain_series)


def _add_intensity_series(kinds) -> None:
    is_ = kinds.add_parser(
        "intensity-series",
        help="several illumination levels at one EM gain set-point",
        description="Simulate an intensity series: several illumination levels at one EM gain "
        "set-point, with one dark stack and its offset/read-noise maps.",
    )
    _common.add_out_or_dir(is_, "output directory (created)")
    is_.add_argument(
        "--levels",
        type=_common.number_list,
        default=[2000.0, 4000.0, 8000.0, 16000.0, 32000.0, 64000.0],
        help="photoelectrons per pixel per frame of each level, e-, comma-separated "
        "(default 2000,4000,8000,16000,32000,64000)",
    )
    is_.add_argument(
        "--labels", type=_common.label_list, default=None, help="level labels (default L1,L2,...)"
    )
    is_.add_argument("--setpoint", type=float, default=1.0, help="EM gain set-point (default 1)")
    is_.add_argument(
        "--em-gain",
        type=float,
        default=None,
        help="true mean EM gain (default: from the set-point)",
    )
    _camera_options(is_)
    is_.set_defaults(func=_run_intensity_series)


def _add_beads(kinds) -> None:
    from ..defaults import BEAD_CAMERA as CAMERA_DEFAULTS
    from ..defaults import BEAD_SIMULATION as BEAD_DEFAULTS

    bd = kinds.add_parser(
        "beads",
        help="isolated beads at several EM gain set-points (bead validation)",
        description="Simulate bead movies: isolated emitters with a pixel-integrated Gaussian "
        "PSF on a uniform background at several EM gain set-points, with a dark stack and "
        "offset/read-noise maps per set-point, truth.json and truth_calibration.nc "
        "(docs/beads.md).",
    )
    _common.add_out_or_dir(bd, "output directory (created)")
    bd.add_argument(
        "--beads",
        type=int,
        default=BEAD_DEFAULTS["beads"],
        help="number of beads (default %(default)s)",
    )
    bd.add_argument(
        "--photoelectrons",
        type=_common.number_list,
        default=[BEAD_DEFAULTS["photoelectrons"]],
        help="photoelectrons per bead per frame, e-: one value or one per bead, "
        f"comma-separated (default {BEAD_DEFAULTS['photoelectrons']:g})",
    )
    bd.add_argument(
        "--width",
        type=float,
        default=BEAD_DEFAULTS["width"],
        help="PSF standard deviation, px (default %(default)s)",
    )
    bd.add_argument(
        "--background",
        type=float,
        default=BEAD_DEFAULTS["background"],
        help="uniform background, e-/px/frame (default %(default)s)",
    )
    bd.add_argument(
        "--min-separation",
        type=float,
        default=BEAD_DEFAULTS["min_separation"],
        help="least distance between beads, px (default %(default)s)",
    )
    bd.add_argument(
        "--margin",
        type=float,
        default=BEAD_DEFAULTS["margin"],
        help="least distance of a bead from the sensor edge, px (default %(default)s)",
    )
    bd.add_argument(
        "--bleaching",
        type=float,
        default=BEAD_DEFAULTS["bleaching"],
        help="fraction of the beads' light lost from the first frame of the series "
        "to the last, set-points recorded in the order given (default %(default)s)",
    )
    bd.add_argument(
        "--halo",
        type=float,
        default=BEAD_DEFAULTS["halo"],
        help="fraction of each bead's light in a wider Gaussian halo: a PSF the "
        "bead fits' Gaussian does not describe (default %(default)s)",
    )
    bd.add_argument(
        "--halo-width",
        type=float,
        default=None,
        help="the halo's standard deviation, px (default 3 x --width)",
    )
    bd.add_argument(
        "--blinking",
        type=float,
        default=BEAD_DEFAULTS["blinking"],
        help="fraction of frames in which each bead is off (default %(default)s)",
    )
    bd.add_argument(
        "--blink-frames",
        type=float,
        default=BEAD_DEFAULTS["blink_frames"],
        help="mean length of a bead's off runs, frames (default %(default)s)",
    )
    bd.add_argument(
        "--repeat",
        type=float,
        default=None,
        metavar="SETPOINT",
        help="record this set-point again at the end of the series (e.g. 1)",
    )
    _setpoint_options(bd)
    _camera_options(bd, CAMERA_DEFAULTS)
    bd.set_defaults(func=_run_beads)
