"""``emccdcal scan DIR [-o OUT]``: write the manifest of a folder of camera files."""

from __future__ import annotations

from pathlib import Path

from . import _common


def add_parser(subparsers):
    p = subparsers.add_parser(
        "scan",
        help="write the manifest of a folder of camera files",
        description="Group a folder's stacks into a gain series or an intensity series by "
        "the settings they record (else by their names: every rule used is said in the "
        "manifest), pair each with its dark (a dark stack, or an offset map and a "
        "read-noise map), check that readout rate, analog gain, ADC bits, binning and "
        "region agree, say which files were used and which skipped and why, and write a "
        "commented manifest (docs/formats.md).",
    )
    p.add_argument("folder", type=Path, metavar="DIR", help="the folder of camera files")
    _common.add_out(
        p,
        "the folder to write manifest.toml into, or the manifest's own "
        "name ending in .toml (default DIR/manifest.toml)",
        required=False,
        overwrite=False,
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing manifest")
    _common.add_quiet(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from ..data.scan import manifest_path, scan, write_manifest

    session = scan(args.folder)
    out = write_manifest(session, manifest_path(args.out, args.folder), overwrite=args.overwrite)
    if not args.quiet:
        print("\n".join(session.summary()))
        print(f"wrote {out}")
    return 0
