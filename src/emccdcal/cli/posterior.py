"""``emccdcal posterior MANIFEST -m METHOD -p ROW,COL -o OUT``: MCMC of single pixels."""

from __future__ import annotations

import sys
from pathlib import Path

from . import _common


def add_parser(subparsers):
    from ..defaults import DEFAULT_FIRST_STEPS, DEFAULT_MAX_STEPS, LIKELIHOOD_METHODS, PRIORS

    p = subparsers.add_parser(
        "posterior",
        help="MCMC posterior of single pixels",
        description="Sample the posterior of a method's free parameters at chosen pixels "
        "(emcee), run until converged, and write OUT/posterior.nc, OUT/posterior.json and "
        "OUT/posterior_<row>_<col>.png.",
    )
    p.add_argument("manifest", type=Path, help="TOML manifest of the acquisitions")
    p.add_argument(
        "--method", "-m", required=True, choices=LIKELIHOOD_METHODS, help="likelihood method"
    )
    p.add_argument(
        "--pixel",
        "-p",
        action="append",
        required=True,
        metavar="ROW,COL",
        type=_common.pixel,
        help="pixel to sample (repeatable)",
    )
    _common.add_out(p)
    _common.add_e_per_adu(p)
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--steps",
        type=int,
        default=None,
        help=f"steps per walker of the first run (default {DEFAULT_FIRST_STEPS})",
    )
    p.add_argument(
        "--max-steps",
        type=int,
        default=DEFAULT_MAX_STEPS,
        help=f"steps per walker before refusing an unconverged chain (default {DEFAULT_MAX_STEPS})",
    )
    p.add_argument("--walkers", type=int, default=None, help="walkers (default max(32, 4F))")
    p.add_argument(
        "--prior",
        choices=PRIORS,
        default="log-uniform",
        help="flat in log-parameters (default) or in physical parameters",
    )
    _common.add_no_figures(p)
    _common.add_em_model(p, auto=False)
    _common.add_device(p)
    _common.add_quiet(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from ..errors import NotConvergedError
    from ..fit.posterior import POSTERIOR_FILE, SUMMARY_FILE, format_summary
    from ..sampling import sample_posterior

    try:
        phi_result = [args.e_per_adu] if isinstance(args.e_per_adu, Path) else []
        with _common.output(
            args,
            args.out,
            inputs=[args.manifest, *phi_result],  # a chained φ's result is an input too
            names=(POSTERIOR_FILE, SUMMARY_FILE),
        ):
            ds = sample_posterior(
                args.manifest,
                args.method,
                args.pixel,
                e_per_adu=args.e_per_adu,
                accept_mismatch=args.accept_mismatch,
                accept_phi=args.accept_phi,
                n_walkers=args.walkers,
                n_steps=args.steps,
                seed=args.seed,
                max_steps=args.max_steps,
                prior=args.prior,
                out=args.out,
                progress=not args.quiet,
                em_model=args.em_model,
                stages=args.stages,
                device=args.device,
            )
            if not args.no_figures:
                from ..report.corner import write_corner_figures

                write_corner_figures(ds, args.out)
    except NotConvergedError as exc:
        print(f"emccdcal posterior: refused: {exc}", file=sys.stderr)
        return 1
    if not args.quiet:
        print(format_summary(ds))
        print(f"wrote {args.out / POSTERIOR_FILE} and {args.out / SUMMARY_FILE}")
    return 0
