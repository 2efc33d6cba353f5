"""``emccdcal check MANIFEST``: data-quality checks, no fitting."""

from __future__ import annotations

import json
from pathlib import Path


def add_parser(subparsers):
    from ..defaults import DEFAULT_DRIFT_THRESHOLD, DEFAULT_K, DRIFT_ALPHA

    p = subparsers.add_parser(
        "check",
        help="data-quality checks of a manifest's acquisitions (no fitting)",
        description="Drift of the frame means, saturated frames, hot/dead/stuck pixels "
        "and read-noise growth, per acquisition (docs/quality.md). Exits 0 when the "
        "checks ran, whatever they found (1 with --strict and a finding).",
    )
    p.add_argument(
        "manifest", type=Path, metavar="MANIFEST", help="TOML manifest (docs/manifest.md)"
    )
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument(
        "--drift-threshold",
        type=float,
        default=DEFAULT_DRIFT_THRESHOLD,
        metavar="PCT",
        help="smallest significant drift (either sign) over an acquisition "
        f"that is a finding, %% of its level (default {DEFAULT_DRIFT_THRESHOLD:g})",
    )
    p.add_argument(
        "--drift-alpha",
        type=float,
        default=DRIFT_ALPHA,
        metavar="ALPHA",
        help="family-wise significance level of the drift tests over the "
        f"acquisitions (default {DRIFT_ALPHA:g})",
    )
    p.add_argument(
        "--unit-root-tests",
        action="store_true",
        help="also report ADF and KPSS p-values of the frame means (never findings)",
    )
    p.add_argument("--strict", action="store_true", help="exit 1 when there is any finding")
    p.add_argument(
        "--k",
        type=float,
        default=DEFAULT_K,
        help=f"robust SDs that make a pixel hot or dead (default {DEFAULT_K:g})",
    )
    p.add_argument(
        "-q", "--quiet", action="store_true", help="print nothing (the findings are in --json)"
    )
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from ..data.manifest import read_manifest
    from ..data.quality import check_manifest, format_report
    from ..errors import ReadNoiseGrowthWarning
    from ._common import recording_warnings

    with recording_warnings() as caught:
        manifest = read_manifest(args.manifest)
        report = check_manifest(
            manifest,
            k=args.k,
            drift_threshold=args.drift_threshold,
            drift_alpha=args.drift_alpha,
            unit_root_tests=args.unit_root_tests,
        )
    # What the readers warned of (a damaged file) is a finding too; read-noise growth
    # is one already.
    read = [str(c.message) for c in caught if not issubclass(c.category, ReadNoiseGrowthWarning)]
    report["warnings"] = list(dict.fromkeys(read)) + report["warnings"]
    if args.json:
        print(json.dumps(report, indent=2, allow_nan=False))
    elif not args.quiet:
        print(format_report(report))
    return 1 if args.strict and report["warnings"] else 0
