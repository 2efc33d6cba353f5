"""``emccdcal demo [-o OUT]``: the whole calibration of the paper on simulated data."""

from __future__ import annotations

from .. import plugins
from ..defaults import DEFAULT_EM_MODEL
from . import _common


def add_parser(subparsers):
    from ..defaults import DEMO_SEED

    p = subparsers.add_parser(
        "demo",
        help="simulate the paper's data and calibrate it (is-adu, then gs)",
        description="Simulate the paper's intensity and gain series with a fixed seed, "
        "calibrate phi with is-adu, then the gains with gs using that phi (the exact "
        "cascade register, the default), print truth against estimate, and the gains the "
        "paper's gamma model reads from the same data.",
    )
    _common.add_out_or_dir(
        p, "output directory (default: a new temporary directory)", required=False
    )
    p.add_argument(
        "--rows", type=_common.positive_int, default=16, help="rows, px (default %(default)s)"
    )
    p.add_argument(
        "--cols", type=_common.positive_int, default=16, help="columns, px (default %(default)s)"
    )
    p.add_argument(
        "--frames",
        type=int,
        default=5000,
        help="frames per acquisition, at least 2 (default %(default)s)",
    )
    p.add_argument(
        "--multiplication",
        **_common.plugin_choice(plugins.REGISTERS, "register model"),
        default=DEFAULT_EM_MODEL,
        help="EM register of the simulated camera: the exact cascade of a real "
        "camera, or the paper's gamma approximation (default %(default)s)",
    )
    p.add_argument("--seed", type=int, default=DEMO_SEED, help="random seed (default %(default)s)")
    p.add_argument("--no-report", action="store_true", help="skip the HTML report")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from ..demo import run_demo
    from ..errors import OptionError

    if args.frames < 2:
        raise OptionError("--frames must be an integer of at least 2")
    import contextlib

    out = _common.output_of(args)
    # an earlier demo's folder is refused, not mixed into (each step reads the one before:
    # nothing is staged; the results are published by calibrate as ever)
    target = (
        contextlib.nullcontext()
        if out is None
        else _common.output(
            args,
            out,
            names=(
                "adu-series/manifest.toml",
                "gain-series/manifest.toml",
                "result-is-adu",
                "result-gs",
            ),
            stage=False,
        )
    )
    with target:
        run_demo(
            out,
            rows=args.rows,
            cols=args.cols,
            frames=args.frames,
            multiplication=args.multiplication,
            seed=args.seed,
            progress=not args.quiet,
            report=not args.no_report,
            overwrite=args.overwrite,
        )
    return 0
