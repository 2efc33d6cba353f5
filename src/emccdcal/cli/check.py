"""``emccdcal check MANIFEST``: data-quality checks, no fitting."""

from __future__ import annotations

import json
from pathlib import Path


def add_parser(subparsers):
    from ..data.quality import DEFAULT_DRIFT_THRESHOLD, DEFAULT_K

    p = subparsers.add_parser(
        "check",
        help="data-quality checks of a manifest's acquisitions (no fitting)",
        description="Stationarity (ADF + KPSS) and linear drift of the frame means, "
        "saturated frames, hot/dead/stuck pixels and read-noise growth, per acquisition. "
        "Exits 0 also when it finds problems; they are listed as findings.",
    )
    p.add_argument("manifest", type=Path, metavar="MANIFEST",
                   help="TOML manifest (docs/manifest.md)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument("--drift-threshold", type=float, default=DEFAULT_DRIFT_THRESHOLD,
                   metavar="PCT", help="|drift| over an acquisition that is a finding, %% "
                   f"(default {DEFAULT_DRIFT_THRESHOLD:g})")
    p.add_argument("--k", type=float, default=DEFAULT_K,
                   help=f"robust SDs that make a pixel hot or dead (default {DEFAULT_K:g})")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="print nothing (the findings are in --json)")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    import warnings

    from ..data.manifest import read_manifest
    from ..data.quality import check_manifest, format_report
    from ..errors import ReadNoiseGrowthWarning

    with warnings.catch_warnings():
        # reported in the table's findings instead
        warnings.simplefilter("ignore", ReadNoiseGrowthWarning)
        manifest = read_manifest(args.manifest)
    report = check_manifest(manifest, k=args.k, drift_threshold=args.drift_threshold)
    if args.json:
        print(json.dumps(report, indent=2, allow_nan=False))
    elif not args.quiet:
        print(format_report(report))
    return 0
